"""kpd: unsupervised 3D keypoints and keypoint-driven cage deformation (KeypointDeformer, CVPR 2021).

``import kpd`` is light: it never imports torch, and heavy modules (Open3D, onnxruntime) load only when used.
"""

from kpd._open3d import defer_plotly_helpers
from kpd.errors import BundleError, DataError, InputError, KpdError, NotFittedError

defer_plotly_helpers()  # Open3D's plotly/dash helpers load on first use, not with every command

__version__ = "0.1.0"

__all__ = ["KpdError", "InputError", "BundleError", "DataError", "NotFittedError", "__version__"]
