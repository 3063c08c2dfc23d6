"""The ``vrnet`` command line (one module per group of commands): ``vrnet train``, ``vrnet eval``, ``vrnet plot``, ``vrnet register``, ...

The ``vrnet`` executable (:func:`run`) ends a short command's process with ``os._exit`` once its
outputs are written and flushed: the interpreter's own teardown of a process that imported torch
takes ~0.35 s on a 2-core machine (a third of a typical ``vrnet register``) and writes nothing.
Training commands exit normally (DDP process groups and DataLoader workers get their clean-up).

The short commands (all but training) let OpenMP's idle threads sleep instead of spinning
(``OMP_WAIT_POLICY=PASSIVE``, unless the environment sets it): beside a process that keeps a core
busy, spinning threads take that core's time from the thread doing the work, and the ICP of
``vrnet register`` took 1.6-1.9x longer with them.
"""
from __future__ import annotations

import argparse
import os
import sys

from vrnet_ext.cli.batch import add_register_batch, run_register_batch
from vrnet_ext.cli.data import add_data, run_data
from vrnet_ext.cli.registering import add_demo, add_register, run_demo, run_register
from vrnet_ext.cli.scene import add_register_scene, run_register_scene
from vrnet_ext.cli.training import (add_eval, add_export, add_plot, add_train, add_train_scene, build_train_config,
                                    run_eval, run_export, run_plot, run_train, run_train_scene)

__all__ = ["build_parser", "build_train_config", "main", "run"]

TRAINING_COMMANDS = ("train", "train-scene")


def build_parser() -> argparse.ArgumentParser:
    from vrnet_ext import __version__

    parser = argparse.ArgumentParser(prog="vrnet", description="VRNet point-cloud registration (vrnet_ext).")
    parser.add_argument("--version", action="version", version=f"vrnet_ext {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    add_train(sub)
    add_eval(sub)
    add_plot(sub)
    add_register(sub)
    add_register_batch(sub)
    add_register_scene(sub)
    add_demo(sub)
    add_export(sub)
    add_train_scene(sub)
    add_data(sub)
    return parser


def _print_warning(command: str):
    """A ``warnings.showwarning`` that prints one line ``vrnet COMMAND: warning: ...`` (no source line)."""
    def show(message, category, filename, lineno, file=None, line=None) -> None:
        print(f"vrnet {command}: warning: {message}", file=sys.stderr)
    return show


def _let_idle_threads_sleep(argv: list[str]) -> None:
    """``OMP_WAIT_POLICY=PASSIVE`` for a short command, before torch loads OpenMP (it reads the
    variable once, when loaded; building the parser loads it)."""
    if (not argv or argv[0] not in TRAINING_COMMANDS) and "torch" not in sys.modules:
        os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def main(argv: list[str] | None = None) -> int:
    _let_idle_threads_sleep(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    import warnings

    previous, warnings.showwarning = warnings.showwarning, _print_warning(args.command)
    try:
        return _dispatch(args)
    finally:
        warnings.showwarning = previous


def _dispatch(args) -> int:
    try:
        commands = {"train": run_train, "eval": run_eval, "plot": run_plot, "register": run_register,
                    "demo": run_demo, "export": run_export, "train-scene": run_train_scene, "data": run_data,
                    "register-batch": run_register_batch, "register-scene": run_register_scene}
        return commands[args.command](args)
    except (FileNotFoundError, ValueError) as exc:
        from vrnet_ext.cli.common import as_flags

        print(f"vrnet {args.command}: error: {as_flags(str(exc), vars(args))}", file=sys.stderr)
        return 2
    except OSError as exc:  # an output that could not be written (atomic_output names it)
        print(f"vrnet {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except MemoryError:
        print(f"vrnet {args.command}: error: out of memory (use fewer points: --icp-points, --network-points, "
              f"--batch-size)", file=sys.stderr)
        return 1
    except RuntimeError as exc:
        first_line = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        print(f"vrnet {args.command}: error: {first_line}", file=sys.stderr)
        return 1


def run() -> None:
    """The ``vrnet`` executable: :func:`main`, then the process ends (see the module docstring)."""
    try:
        status = main()
    except SystemExit as exc:  # argparse's --help and usage errors (an int code, the message printed)
        if exc.code is None or isinstance(exc.code, int):
            status = exc.code or 0
        else:
            print(exc.code, file=sys.stderr)
            status = 1
    sys.stdout.flush()
    sys.stderr.flush()
    if len(sys.argv) > 1 and sys.argv[1] in TRAINING_COMMANDS:
        sys.exit(status)
    os._exit(status)
