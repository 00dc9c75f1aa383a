"""Pure numpy/scipy core: types, checks, camera & frustum, voxels, association, fusion, boxes, the step.

Nothing here does I/O; the per-frame step talks to the world only through the ports in ``arcloud.ports``.
"""
