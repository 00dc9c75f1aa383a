"""The simulator: procedural rooms, a ray-cast renderer, users walking through them, a faulty 2D detector.

- ``room``: ``generate_room(seed)`` builds a z-up room mesh with furniture of the five classes and
  exact ground-truth boxes.
- ``render``: ``MeshRenderer`` ray-casts any triangle mesh (a generated room or a real scan) into colour,
  z-depth and per-pixel instance ids with Open3D's ``RaycastingScene``.
- ``trajectory``: ``plan_walk`` plans one user's smooth walk through free floor space looking at targets,
  the default walk or one in a ``WalkStyle`` (eye height, speed, coverage, glances, fast turns, jitter).
- ``detector``: ``SimulatedDetector`` turns the true instance image into detections with seeded faults
  (``DetectorFaults``); the same faults model depth and pose noise.
- ``sequence``: ``simulate_sequence`` renders a walk into validated ``Frame`` objects.

Import the submodules; nothing here is imported eagerly (Open3D loads only when a renderer is built).
"""
