"""arcloud: multi-user, scalable 3D object detection in an AR cloud.

RGB-D frames with camera poses come in from many devices; one shared map of 3D objects (sparse voxels,
labels, boxes) in a common world frame comes out. See README.md for the two commands a new user needs.
"""

__version__ = "0.1.0"
