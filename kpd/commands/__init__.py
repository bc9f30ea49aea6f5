"""One module per ``kpd`` subcommand.

Each module defines ``HELP`` (one line), ``EXAMPLE`` (shown under ``--help``), ``add_arguments(parser)`` and
``run(args) -> int``. Modules import only light things at the top; heavy work (Open3D, onnxruntime, torch) is imported
inside ``run`` so that ``kpd --help`` stays fast and torch is loaded only by ``train`` and ``export``.
"""

from __future__ import annotations

import os
from pathlib import Path

from kpd.errors import InputError

# name -> module, in the order shown by `kpd --help`.
COMMANDS = {
    "demo": "kpd.commands.demo",
    "train": "kpd.commands.train",
    "export": "kpd.commands.export",
    "keypoints": "kpd.commands.keypoints",
    "deform": "kpd.commands.deform",
    "align": "kpd.commands.align",
    "sample": "kpd.commands.sample",
    "scan": "kpd.commands.scan",
    "view": "kpd.commands.view",
    "render": "kpd.commands.render",
    "eval": "kpd.commands.eval",
    "bench": "kpd.commands.bench",
}


def check_output(out: str | os.PathLike, *, force: bool = False, inputs: tuple = ()) -> Path:
    """Refuse an output path that would overwrite an input, or an existing file unless ``force``.

    Parameters
    ----------
    out : path the command will write (atomically, after all work is done).
    force : allow replacing an existing output (never an input).
    inputs : paths the command reads.
    """
    path = Path(out)
    for source in inputs:
        if source is not None and Path(source).exists() and path.exists() and path.resolve() == Path(source).resolve():
            raise InputError(f"output {path} is also an input; choose another --out")
    if path.exists() and not force:
        raise InputError(f"output {path} exists; pass --force to replace it")
    if not path.parent.exists():
        raise InputError(f"output folder {path.parent} does not exist")
    return path
