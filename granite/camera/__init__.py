"""Camera models with Basalt's parametrisations: pinhole, Kannala-Brandt (kb4), Double Sphere
(ds), all vectorised with numba kernels.

Points are in the camera frame (x right, y down, z forward); pixels ``(u, v) = (column, row)``
with the top-left pixel centre at (0, 0); bearings are unit vectors.
"""

from granite.camera.base import CameraModel
from granite.camera.double_sphere import DoubleSphereCamera
from granite.camera.factory import CAMERA_MODELS, make_camera
from granite.camera.kannala_brandt import KannalaBrandtCamera
from granite.camera.pinhole import PinholeCamera

__all__ = [
    "CameraModel",
    "PinholeCamera",
    "KannalaBrandtCamera",
    "DoubleSphereCamera",
    "CAMERA_MODELS",
    "make_camera",
]
