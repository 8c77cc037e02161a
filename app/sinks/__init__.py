"""The app's implementations of the core's Sink protocol (vo_core.events.Sink).

files.py writes the result files of ``fdmo run``; rerun_sink.py records a .rrd; viser_view.py serves the live
page. Nothing is imported here, so that a run without a viewer never loads rerun or viser.
"""
