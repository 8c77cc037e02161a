"""The hybrid's decision (FDMO Fig. 2): what each half says about a frame (evidence.py), and what becomes of it
(decide.py, a pure function of that evidence and the config). The system gathers the one and carries out the other."""
