"""arcloud: multi-user, scalable 3D object detection in an AR cloud.

RGB-D frames with camera poses come in from many devices; one shared map of 3D objects (sparse voxels,
labels, boxes) in a common world frame comes out. See README.md for the two commands a new user needs.

The API lives in the subpackages (``arcloud.client``, ``arcloud.errors``, ``arcloud.core``, ...);
importing this package loads nothing else. Its exported names are pinned by ``tests/test_public_api.py``.
"""

__version__ = "0.1.0"

__all__ = ["__version__"]
