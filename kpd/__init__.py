"""kpd: unsupervised 3D keypoints and keypoint-driven cage deformation (KeypointDeformer, CVPR 2021).

``import kpd`` is light: it never imports torch, and heavy modules (Open3D, onnxruntime) load only when used.
"""

import os

# onnxruntime's own builds since 1.29 report to Microsoft on Linux too (a device id under ~/.cache/Microsoft, a
# session file in the temporary folder, events uploaded over the network) unless this is set before onnxruntime
# starts: kpd sends nothing anywhere and writes only what it is asked to. A user's own setting is kept.
os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")

from kpd._open3d import defer_plotly_helpers  # after the setting above, which must come first
from kpd.errors import BundleError, DataError, InputError, KpdError, NotFittedError

defer_plotly_helpers()  # Open3D's plotly/dash helpers load on first use, not with every command

__version__ = "0.1.0"

__all__ = ["KpdError", "InputError", "BundleError", "DataError", "NotFittedError", "__version__"]
