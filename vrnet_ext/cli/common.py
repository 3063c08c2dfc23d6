"""Argument types and helpers shared by the ``vrnet`` commands: each checks its value before any
work starts and names what is wrong."""
from __future__ import annotations

import argparse
import json
import math
import os
import re
import sys
import tempfile
from collections.abc import Iterable, Iterator
from contextlib import contextmanager, nullcontext, redirect_stdout
from pathlib import Path

from vrnet_ext.names import AUTO_DEVICE


class DefaultsHelpFormatter(argparse.HelpFormatter):
    """Shows each option's default after its help, a list as its items (``1 16 64``), unless the help
    already says what the default is (options whose default ``None`` stands for something computed)
    or there is none to show (``None``, empty, a flag's ``False``)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if isinstance(action, Switch) and isinstance(default, bool) and "default:" not in text:
            return f"{text} (default: {action.option_strings[0 if default else 1]})"
        if ("default:" in text or default is None or default is argparse.SUPPRESS or action.nargs == 0
                or default in ("", [])):
            return text
        shown = " ".join(map(str, default)) if isinstance(default, (list, tuple)) else str(default)
        return f"{text} (default: {shown.replace('%', '%%')})"

    def _format_action_invocation(self, action: argparse.Action) -> str:
        if isinstance(action, Switch):  # --name, --no-name: the old style's value is not shown
            return ", ".join(action.option_strings)
        return super()._format_action_invocation(action)

    def _format_args(self, action: argparse.Action, default_metavar: str) -> str:
        return "" if isinstance(action, Switch) else super()._format_args(action, default_metavar)


def parse_bool(text: str) -> bool:
    value = text.strip().lower()
    if value in ("1", "true", "yes", "on"):
        return True
    if value in ("0", "false", "no", "off"):
        return False
    raise argparse.ArgumentTypeError(f"expected 1/0/true/false, got {text!r}")


class Switch(argparse.BooleanOptionalAction):
    """Every yes/no option of the ``vrnet`` commands, in one style: ``--name`` turns it on,
    ``--no-name`` off. With ``values=True`` (only for commands without positional arguments, which a
    value could swallow) the style of 0.1, ``--name 1`` / ``--name 0``, still works and warns."""

    def __init__(self, option_strings, dest, values: bool = False, **kwargs):
        super().__init__(option_strings, dest, **kwargs)
        if values:
            self.nargs = "?"

    def __call__(self, parser, namespace, values, option_string=None):
        if values is None or option_string.startswith("--no-"):
            super().__call__(parser, namespace, values, option_string)
            return
        try:
            value = parse_bool(values)
        except argparse.ArgumentTypeError:
            parser.error(f"argument {option_string}: takes no value ({' or '.join(self.option_strings)}), "
                         f"got {values!r}")
        now = self.option_strings[0 if value else 1]
        print(f"{parser.prog}: warning: {option_string} {values} is now {now}", file=sys.stderr)
        setattr(namespace, self.dest, value)


def int_at_least(low: int):
    """An argparse type: an integer >= ``low``, with an error that says so."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer >= {low}, got {text!r}") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"expected an integer >= {low}, got {value}")
        return value

    parse.__name__ = f"integer >= {low}"
    return parse


positive_int = int_at_least(1)


nonnegative_int = int_at_least(0)


def positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"expected a finite number > 0, got {text}")
    return value


def unit_interval(text: str) -> float:
    """A number in [0, 1]."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got {text!r}") from None
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got {text}")
    return value


def existing_folder(text: str) -> str:
    """A folder that exists."""
    if not Path(text).expanduser().is_dir():
        raise argparse.ArgumentTypeError(f"{text!r} is not a folder")
    return text


def memory_size(text: str) -> int:
    """A memory size such as 2GB, 512MB, 1.5G or a plain byte count -> bytes."""
    from vrnet_ext.registration.budget import parse_memory_size

    try:
        return parse_memory_size(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def device_name(text: str) -> str:
    """A device name torch knows and this machine has (checked before any work starts)."""
    import torch

    try:
        device = torch.device(text)
    except (RuntimeError, ValueError):
        raise argparse.ArgumentTypeError(f"not a device name: {text!r} (e.g. cpu, cuda, cuda:1)") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise argparse.ArgumentTypeError(f"{text!r}: no CUDA device is available here")
    if device.type not in ("cpu", "cuda"):
        raise argparse.ArgumentTypeError(f"{text!r}: only cpu and cuda devices are supported")
    return text


def device_or_auto(text: str) -> str:
    """``auto`` (CUDA when there is one) or a device of :func:`device_name`."""
    return text if text == AUTO_DEVICE else device_name(text)


def checkpoint_or_shipped(text: str) -> str:
    """A checkpoint file as given, or a shipped model's name (e.g. vrnet-pv-upc-rcp) as its weights
    file's path (recorded as such in the run's config)."""
    if Path(text).expanduser().is_file():
        return text
    from vrnet_ext.model.pretrained import available, weights_path

    if text in available("vrnet"):
        return str(weights_path(text))
    raise argparse.ArgumentTypeError(f"{text!r} is neither a file nor a shipped model (one of: "
                                     f"{', '.join(available('vrnet'))})")


def output_folder(text: str) -> str:
    """A folder to create or fill: not an existing file, and under a writable existing ancestor."""
    path = Path(text).expanduser().resolve()
    if path.exists() and not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text!r} is a file; give a folder")
    ancestor = next(p for p in (path, *path.parents) if p.exists())
    if not ancestor.is_dir() or not os.access(ancestor, os.W_OK):
        raise argparse.ArgumentTypeError(f"{text!r}: {ancestor} is not a writable folder")
    return text


def writable_path(text: str) -> str:
    """An output file whose folder exists and takes a new file, that is not a folder itself, and
    that can be opened for writing if it exists (an immutable file, a read-only or pseudo file
    system: /sys, /proc) - checked before the work, not after it, without changing anything. A
    device or FIFO passes: it is written into."""
    try:
        path = Path(text).expanduser().resolve()
    except (RuntimeError, OSError) as error:  # a symlink loop
        raise argparse.ArgumentTypeError(f"{text!r}: cannot be followed to a file ({error})") from None
    if not path.parent.is_dir():
        raise argparse.ArgumentTypeError(f"{text!r}: the folder {path.parent} does not exist")
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text!r} is a folder; give a file name")
    if path.exists() and not path.is_file():
        return text
    try:
        descriptor, probe = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".probe", dir=path.parent)
        os.close(descriptor)
        os.unlink(probe)
        if path.exists():
            os.close(os.open(path, os.O_WRONLY | os.O_APPEND))
    except OSError as error:
        raise argparse.ArgumentTypeError(f"{text!r}: cannot be written ({error.strerror or error})") from None
    return text


class RenamedOption(argparse.Action):
    """An option's old name, hidden from ``--help``: it still works, and warns with the new name."""

    def __call__(self, parser, namespace, values, option_string=None):
        new = next(a.option_strings[0] for a in parser._actions if a.dest == self.dest and a is not self)
        print(f"{parser.prog}: warning: {option_string} is now {new}", file=sys.stderr)
        setattr(namespace, self.dest, values)


PICTURE_SUFFIXES = (".png", ".pdf", ".svg", ".jpg", ".jpeg")


def picture_path(text: str) -> str:
    """A picture to write (:func:`writable_path`) whose name says its format (checked before the work)."""
    if Path(text).suffix.lower() not in PICTURE_SUFFIXES:
        raise argparse.ArgumentTypeError(f"{text!r}: give a picture file name ending in "
                                         f"{', '.join(PICTURE_SUFFIXES)}")
    return writable_path(text)


MAX_VIEW_POINTS = 200_000  # train-scene: the InfoNCE matrix grows as the square of the view's points


def view_points(text: str) -> int:
    value = positive_int(text)
    if value > MAX_VIEW_POINTS:
        raise argparse.ArgumentTypeError(f"{value} is more than {MAX_VIEW_POINTS} points per view (memory grows "
                                         f"as its square)")
    return value


DATA_DIR_HELP = ("folder holding modelnet40_1024_{train,test}.h5, made by `vrnet data modelnet40` (default: "
                 "$VRNET_DATA/modelnet40; else ../shared/data/modelnet40 beside a source checkout; else "
                 "~/.local/share/vrnet_ext/modelnet40)")


STDOUT = "-"  # --json -: the record on standard output
# The library's messages name its arguments; the command line's user knows the flags. Arguments whose
# flag is not the argument's own name:
RENAMED = {"IcpSettings.max_iterations": "--icp-iterations"}


def as_flags(message: str, options: Iterable[str] = ()) -> str:
    """A library message with the arguments it names written as command-line flags: those of
    :data:`RENAMED`, any of the command's ``options`` (argument names, e.g. ``num_points``) with an
    underscore wherever it stands, and a one-word option where the message opens with it."""
    flags = dict(RENAMED)
    flags.update({name: "--" + name.replace("_", "-") for name in options if "_" in name})
    if flags:
        pattern = r"(?<![\w.-])(" + "|".join(map(re.escape, sorted(flags, key=len, reverse=True))) + r")(?![\w])"
        message = re.sub(pattern, lambda match: flags[match.group(1)], message)
    first = message.split(" ", 1)[0]
    if first in options and "_" not in first:
        message = "--" + message
    return message


def json_output(text: str) -> str:
    """A ``--json`` argument: a file as :func:`writable_path` checks it, or ``-`` for standard output."""
    return text if text == STDOUT else writable_path(text)


@contextmanager
def report_to(json_path: str | Path | None) -> Iterator[None]:
    """The block's human-readable report goes to standard error when the JSON record takes standard
    output (``--json -``), so that a pipe receives the record alone."""
    with redirect_stdout(sys.stderr) if str(json_path) == STDOUT else nullcontext():
        yield


def report_and_record(args, work) -> int:
    """Runs ``work(args)`` (which prints a report and returns a record), the report on standard error
    when ``--json -`` takes standard output, then writes the record where ``--json`` says."""
    with report_to(args.json):
        record = work(args)
    if args.json:
        write_json(args.json, record)
    return 0


def write_json(path: str | Path, record: dict) -> None:
    """The record as JSON at ``path`` (atomically; a device or FIFO is written into), or on standard
    output for ``-``."""
    from vrnet_ext.geometry.atomic import atomic_output

    text = json.dumps(record, indent=1)
    if str(path) == STDOUT:
        print(text)
        return
    with atomic_output(path) as temporary:
        temporary.write_text(text)
    print(f"wrote {path}")
