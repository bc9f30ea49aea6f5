"""One module per ``kpd`` subcommand.

Each module defines ``HELP`` (one line), ``EXAMPLE`` (shown under ``--help``), ``add_arguments(parser)`` and
``run(args) -> int``. Modules import only light things at the top; heavy work (Open3D, onnxruntime, torch) is imported
inside ``run`` so that ``kpd --help`` stays fast and torch is loaded only by ``train`` and ``export``.
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import os
from pathlib import Path

from kpd.errors import KpdError

# name -> module, in the order shown by `kpd --help`.
COMMANDS = {
    "demo": "kpd.commands.demo",
    "train": "kpd.commands.train",
    "export": "kpd.commands.export",
    "keypoints": "kpd.commands.keypoints",
    "deform": "kpd.commands.deform",
    "align": "kpd.commands.align",
    "sample": "kpd.commands.sample",
    "amplify": "kpd.commands.amplify",
    "scan": "kpd.commands.scan",
    "rig": "kpd.commands.rig",
    "view": "kpd.commands.view",
    "render": "kpd.commands.render",
    "eval": "kpd.commands.eval",
    "bench": "kpd.commands.bench",
}


def check_output(out: str | os.PathLike, *, force: bool = False, inputs: tuple = (), option: str = "--out",
                 kind: str = "file", formats: tuple | None = None, what: str = "") -> Path:
    """Refuse an output that is an input or holds one, an unwritable folder, or an existing file unless ``force``
    (one line naming ``option``); see :func:`kpd.io.check_output`. Commands write through :class:`kpd.io.Outputs`,
    which makes this check for every output it registers."""
    from kpd.io import check_output as check

    return check(out, option=option, force=force, inputs=inputs, kind=kind, formats=formats, what=what)


# --- options checked before any work: argparse types (one line naming the option, exit status 2) ----------------


def integer(minimum: int | None = None, maximum: int | None = None):
    """An argparse ``type`` for an integer option in [minimum, maximum] (either bound optional)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be an integer; got {text!r}") from None
        _bounds(value, minimum, maximum)
        return value

    parse.__name__ = "integer"
    return parse


def number(minimum: float | None = None, maximum: float | None = None, *, positive: bool = False):
    """An argparse ``type`` for a finite number in [minimum, maximum]; ``positive``: strictly above 0."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be a number; got {text!r}") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"must be a finite number; got {text!r}")
        if positive and value <= 0:
            raise argparse.ArgumentTypeError(f"must be greater than 0; got {text}")
        _bounds(value, minimum, maximum)
        return value

    parse.__name__ = "number"
    return parse


def _bounds(value, minimum, maximum) -> None:
    if minimum is not None and maximum is not None and not minimum <= value <= maximum:
        raise argparse.ArgumentTypeError(f"must lie in [{minimum}, {maximum}]; got {value:g}")
    if minimum is not None and value < minimum:
        raise argparse.ArgumentTypeError(f"must be at least {minimum}; got {value:g}")
    if maximum is not None and value > maximum:
        raise argparse.ArgumentTypeError(f"must be at most {maximum}; got {value:g}")


def folder(text: str) -> str:
    """An argparse ``type`` for an existing folder (a file or a missing path is named as such)."""
    p = Path(text)
    if p.is_file():
        raise argparse.ArgumentTypeError(f"must be a folder; {text} is a file")
    if not p.exists():
        raise argparse.ArgumentTypeError(f"folder {text} does not exist")
    return text


def existing(text: str) -> str:
    """An argparse ``type`` for an input path (file or folder) that must exist."""
    if not os.path.exists(text):
        raise argparse.ArgumentTypeError(f"{text} does not exist")
    return text


def add_check(parser: argparse.ArgumentParser, check) -> None:
    """Run ``check(args)`` (raising :class:`~kpd.errors.InputError`) after parsing and before the command's work."""
    parser.set_defaults(_checks=[*(parser.get_default("_checks") or []), check])


def run_checks(args: argparse.Namespace) -> None:
    for check in getattr(args, "_checks", None) or []:
        check(args)


def shipped_names() -> str:
    """The shipped models' names for ``--help`` texts: ``chair, shoe, table``."""
    from kpd.bundle import shipped_bundles

    return ", ".join(shipped_bundles()) or "none"


# --- the train extra (pyproject.toml): torch and the ONNX exporter, which kpd's runtime never needs ----------------

TRAIN_EXTRA = ("torch", "onnx", "onnxscript")  # the modules of `pip install "kpd[train]"` the commands import


def train_extra_missing(module: str) -> str:
    """The one line that says a module of the train extra is not installed, and how to get it (torch's default build
    on Linux brings CUDA's libraries, gigabytes that a CPU has no use for: its CPU-only build comes first)."""
    return (f"{module} is not installed: this command needs kpd's train extra, pip install \"kpd[train]\" (for "
            f"torch's CPU-only build, first: pip install torch --index-url https://download.pytorch.org/whl/cpu)")


def require_train_extra(*modules: str) -> None:
    """Refuse a command before any work when a module of the train extra it needs is not installed
    (:class:`~kpd.errors.KpdError`, one line naming the extra); ``modules`` default to all of :data:`TRAIN_EXTRA`."""
    for module in modules or TRAIN_EXTRA:
        if importlib.util.find_spec(module) is None:
            raise KpdError(train_extra_missing(module))
