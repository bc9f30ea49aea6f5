"""Evaluation metrics (numpy, torch-free), one module per kind:

- :mod:`kpd.metrics.labelfree`: keypoint stability, distance to the surface, mirror consistency, the alignment chamfer;
- :mod:`kpd.metrics.annotated`: protocols on annotated data (PCK by regression, part correspondence, DAS, coverage);
- :mod:`kpd.metrics.edits`: edit quality (locality, folds, distortion, semantic edits, the prior's response).

Every name is importable from ``kpd.metrics`` itself.
"""

from __future__ import annotations

from kpd.metrics.annotated import *  # noqa: F401,F403
from kpd.metrics.annotated import __all__ as _annotated
from kpd.metrics.edits import *  # noqa: F401,F403
from kpd.metrics.edits import _fold_share, _turned  # noqa: F401  (used by the tests of the rig's straightening)
from kpd.metrics.edits import __all__ as _edits
from kpd.metrics.labelfree import *  # noqa: F401,F403
from kpd.metrics.labelfree import __all__ as _labelfree

__all__ = [*_labelfree, *_annotated, *_edits]
