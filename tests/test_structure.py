"""The code's shape that DESIGN.md §4 promises: commands stay thin and apart, modules stay readable."""

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "ddsgen"


def _imported_modules(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
            names.update(f"{node.module}.{a.name}" for a in node.names)
        elif isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
    return names


def test_no_command_module_imports_another():
    commands = {p.stem for p in (PACKAGE / "commands").glob("*.py") if p.stem != "__init__"}
    offenders = []
    for path in (PACKAGE / "commands").glob("*.py"):
        for module in _imported_modules(path):
            parts = module.split(".")
            if parts[:2] == ["ddsgen", "commands"] and len(parts) > 2 and parts[2] in commands:
                offenders.append(f"{path.name} imports {module}")
    assert not offenders, offenders


def test_the_sensor_never_imports_cli_runner_or_writers():
    forbidden = ("ddsgen.cli", "ddsgen.commands", "ddsgen.runner", "ddsgen.io.framefiles", "ddsgen.io.bop_writer")
    offenders = [f"{path.relative_to(PACKAGE)} imports {m}" for path in (PACKAGE / "sensor").rglob("*.py")
                 for m in _imported_modules(path) if m.startswith(forbidden)]
    assert not offenders, offenders


def test_no_module_over_600_lines():
    long = {str(p.relative_to(PACKAGE)): n for p in PACKAGE.rglob("*.py") if (n := len(p.read_text().splitlines())) > 600}
    assert not long, long
