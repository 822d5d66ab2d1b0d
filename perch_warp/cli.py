"""Command line: `python -m perch_warp IMAGE --mesh MESH --camera CAMERA.json ...` and subcommands.

Subcommands: `demo` (a self-made scene, offline), `eval` (BOP datasets), `synth`
(synthetic BOP scenes), `bench` (speed measurements). Bad input ends with one line on stderr and exit code 1.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from .errors import PerchError
from .report import log

# The main command and each subcommand is a module exposing add_arguments(parser) and run(args) -> int,
# imported only when chosen (the estimate's Warp and torch take seconds to import, synth needs neither).
ESTIMATE = "perch_warp.estimate"
SUBCOMMANDS = {
    "demo": ("perch_warp.demo", "run the whole pipeline on a scene the project makes itself (offline)"),
    "eval": ("perch_warp.eval.command", "evaluate on a BOP-format dataset (ADD-S, AUC, plots)"),
    "synth": ("perch_warp.synth.command", "generate photorealistic synthetic BOP test scenes"),
    "bench": (
        "perch_warp.bench.command",
        "time the reference workload, a ray-casting microbenchmark and its Open3D peer",
    ),
}


# --- entry point --------------------------------------------------------------------------------


def _parser(prog: str = "python -m perch_warp") -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=prog,
        description="Find where a known object sits on a table from one RGB image (PERCH Color Only on NVIDIA Warp). "
        f"Subcommands: {', '.join(SUBCOMMANDS)} (see `{prog} SUBCOMMAND --help`).",
    )
    importlib.import_module(ESTIMATE).add_arguments(p)
    return p


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        if argv and argv[0] in SUBCOMMANDS:
            module_name, help_text = SUBCOMMANDS[argv[0]]
            p = argparse.ArgumentParser(prog=f"python -m perch_warp {argv[0]}", description=help_text)
            module = importlib.import_module(module_name)
            module.add_arguments(p)
            return int(module.run(p.parse_args(argv[1:])) or 0)
        return int(importlib.import_module(ESTIMATE).run(_parser().parse_args(argv)) or 0)
    except PerchError as e:
        log("perch_warp: error: " + " ".join(str(e).split()))  # always one line
        return 1
    except KeyboardInterrupt:
        log("perch_warp: interrupted")
        return 130
