"""The simulator: procedural rooms, users walking through them, a faulty 2D detector.

- ``room``: ``generate_room(seed)`` builds a z-up room mesh with furniture of the five classes and
  exact ground-truth boxes (``RoomObject.box``); ``room_renderer`` and ``room_walk`` hand a room to
  the shared ``arcloud.virtual_camera`` renderer and walk planner. Rooms are built from
  ``primitives`` (boxes, cylinders, ellipsoids), shaped into ``furniture`` and placed by ``layout``.
- ``detector``: ``SimulatedDetector`` turns the true instance image into detections with seeded faults
  (``DetectorFaults``); the same faults model depth and pose noise. ``FrameTruths`` carries the
  frames' true instance images from the sequence to the detector, when the caller passes it to both.
- ``sequence``: ``simulate_sequence`` renders a walk into validated ``Frame`` objects.

Import the submodules; nothing here is imported eagerly (Open3D loads only when a renderer is built).
Nothing is cached at module level: renderers and truths belong to whoever built them.
"""
