"""The house's arrows (ARCHITECTURE.md beside the project, issue 46), read from the source: every module under
vo_core/ is parsed with ``ast`` and each of its imports, wherever it stands (top, in a function, under
TYPE_CHECKING), is checked against the arrows that hold:

- the direct half and the feature half never import each other (what both need lives below them in geometry/:
  the motion model, corner detection and KLT tracking), nor anything above them (init, front ends, the system,
  the composed config);
- the hybrid's decision (fdmo/) may import the direct and the feature half, and nothing above it (the system, the
  front ends, init, the mapping threads); the halves and init never import it;
- the initializers never import the KLT baseline, nor any front end, nor the system; they use the feature half
  in one place only, the start check's epipolar witness (ORB matches), which the registry hands to the direct half;
- geometry imports nothing of ours but vo_core.compiled and vo_core.errors;
- nothing in vo_core imports the face (app) or a viewer (rerun, viser).

A broken arrow fails with the file, the line and the import.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "vo_core"


def module_files() -> list[Path]:
    """Every Python file of the package (vo_core/data holds files the package ships, not code)."""
    return sorted(path for path in PACKAGE.rglob("*.py") if path.relative_to(PACKAGE).parts[0] != "data")


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path) -> list[tuple[int, str, list[str]]]:
    """(line, statement, dotted names) of every import statement of ``path``; ``from a import b`` names both ``a``
    and ``a.b`` (b may be a module), relative imports resolved against the file's package."""
    package = module_name(path).split(".")
    if path.name != "__init__.py":
        package = package[:-1]
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.append((node.lineno, ast.unparse(node), [alias.name for alias in node.names]))
        elif isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            module = ".".join([*base, *([node.module] if node.module else [])])
            names = [module, *(f"{module}.{alias.name}" for alias in node.names if alias.name != "*")]
            found.append((node.lineno, ast.unparse(node), names))
    return found


def within(name: str, *packages: str) -> bool:
    return any(name == package or name.startswith(package + ".") for package in packages)


def broken_arrows(importer: tuple[str, ...], forbidden, allowed: tuple[str, ...] = ()) -> list[str]:
    """'file:line: statement' for every import statement of a module in ``importer`` (packages) that imports a name
    ``forbidden(name)`` refuses, except in files ending in one of ``allowed``."""
    broken = []
    for path in module_files():
        if not within(module_name(path), *importer) or path.as_posix().endswith(allowed):
            continue
        for line, statement, names in imports(path):
            if any(forbidden(name) for name in names):
                broken.append(f"{path.relative_to(ROOT).as_posix()}:{line}: {statement}")
    return broken


def fail_on(broken: list[str], arrow: str) -> None:
    if broken:
        pytest.fail(f"{arrow}, but:\n  " + "\n  ".join(broken), pytrace=False)


# vo_core.klt: the baseline's old home; vo_core.fdmo: the hybrid's decision, where the house puts it.
ABOVE_THE_HALVES = ("vo_core.init", "vo_core.front_ends", "vo_core.klt", "vo_core.system", "vo_core.config",
                    "vo_core.fdmo")

ARROWS = {
    "direct never imports the feature half": (
        ("vo_core.direct",), lambda name: within(name, "vo_core.features")),
    "features never imports the direct half": (
        ("vo_core.features",), lambda name: within(name, "vo_core.direct")),
    "the halves import nothing above them": (
        ("vo_core.direct", "vo_core.features"), lambda name: within(name, *ABOVE_THE_HALVES)),
    "init never imports the KLT baseline, a front end or the system": (
        ("vo_core.init",), lambda name: within(name, "vo_core.klt", "vo_core.front_ends", "vo_core.system")),
    "direct, features and init never import the hybrid's decision (fdmo)": (
        ("vo_core.direct", "vo_core.features", "vo_core.init"), lambda name: within(name, "vo_core.fdmo")),
    "fdmo imports the halves and what lies below them, never the system, a front end, init or the mapping threads": (
        ("vo_core.fdmo",), lambda name: within(name, "vo_core.system", "vo_core.front_ends", "vo_core.klt",
                                               "vo_core.init", "vo_core.mapping_thread")),
    "geometry imports nothing of ours but vo_core.compiled and vo_core.errors": (
        ("vo_core.geometry",),
        lambda name: within(name, "vo_core") and name != "vo_core"
        and not within(name, "vo_core.geometry", "vo_core.compiled", "vo_core.errors")),
    "vo_core never imports app, rerun or viser": (
        ("vo_core",), lambda name: within(name, "app", "rerun", "viser")),
}


@pytest.mark.parametrize("arrow", list(ARROWS))
def test_arrow(arrow):
    importer, forbidden = ARROWS[arrow]
    fail_on(broken_arrows(importer, forbidden), arrow)


def test_init_uses_the_feature_half_only_for_the_start_witness():
    broken = broken_arrows(("vo_core.init",), lambda name: within(name, "vo_core.features"),
                           allowed=("vo_core/init/epipolar_check.py",))
    fail_on(broken, "init uses the feature half only in the start check's witness (init/epipolar_check.py)")


def test_the_reader_sees_every_import():
    """The checks above cannot pass by reading nothing: the package is all there, and imports inside functions
    count."""
    names = {module_name(path) for path in module_files()}
    assert {"vo_core.system", "vo_core.direct.odometry", "vo_core.features.orb", "vo_core.init.registry",
            "vo_core.geometry.lie", "vo_core.front_ends", "vo_core.front_ends.klt.pipeline"} <= names

    def imported(path: Path) -> set[str]:
        return {name for _, _, names in imports(path) for name in names}

    assert "vo_core.front_ends.klt.pipeline" in imported(PACKAGE / "front_ends" / "__init__.py")  # in a function
    assert "vo_core.features.orb.OrbExtractor" in imported(PACKAGE / "init" / "epipolar_check.py")
    assert broken_arrows(("vo_core.direct",), lambda name: within(name, "vo_core.geometry"))  # it does use geometry
    assert broken_arrows(("vo_core.fdmo",), lambda name: within(name, "vo_core.direct"))  # the decision reads direct's
    assert broken_arrows(("vo_core.system",), lambda name: within(name, "vo_core.fdmo"))  # the system decides by it
