"""The tests of tools/ scripts: load one as a module, write the per_target.csv of a made-up eval run."""

import csv
import importlib.util
from pathlib import Path
from types import ModuleType

TOOLS = Path(__file__).resolve().parents[1] / "tools"


def load_tool(name: str) -> ModuleType:
    """tools/NAME.py as a module (tools/ is not a package: its scripts are run by path)."""
    spec = importlib.util.spec_from_file_location(name, TOOLS / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def eval_run(folder: Path, columns: list[str], rows: list[tuple]) -> Path:
    """A folder holding only per_target.csv with these columns and rows, as `perch_warp eval` writes it."""
    folder.mkdir()
    with (folder / "per_target.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(columns)
        w.writerows(rows)
    return folder
