"""File formats a map is exported in, as pure encoders of plain arrays and records (no I/O, no store):

- ``ply``: voxels as a binary PLY point cloud with a colour per point (Open3D, MeshLab, CloudCompare);
- ``gltf``: boxes as a binary glTF 2.0 (GLB) scene, one node per object with its label and score in
  ``extras`` (Blender, three.js, any glTF viewer);
- ``scannet``: ScanNet benchmark prediction files (the per-scene instance list with per-vertex masks
  where a mesh is given, and the boxes), and their reader;
- ``colors``: one colour per class and per object, shared by the exports.

The service (``GET /v1/maps/{map}/export``) and ``arcloud export`` turn a map's objects into these inputs.
"""
