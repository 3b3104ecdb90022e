"""The scanner: from frames, the robot's reports and a calibration to a point cloud, an edge
cloud and the part's pose in the gripper. Plain functions and small dataclasses over numpy
arrays, one subpackage per concern, each with its public face in its ``__init__``:

- ``geometry``: the camera, its lens, planes and mirrors, triangulation (paper, section II),
  and the calibration file that holds what the scanner knows of its cell;
- ``stripe``: the laser stripe's sub-pixel centre per image column;
- ``marker``: the gripper's LED in the direct and the mirror views;
- ``edges``: edge points along each profile, their kinds, the model's edges;
- ``pose``: the scan registered against the CAD model, its uncertainty, the act verdict;
- ``pipeline``: one pass from frames to a scan (trigger, exposure, per-frame work, the
  accumulator), the cross-check against the robot, the finisher and the report;
- ``recording``: a pass recorded to a folder and replayed;
- ``calibration``: calibrating a cell (the plan, the session, the light plane, the views);
- ``io``: PLY, scan files, mesh files, the UR controller's protocol and poses;
- ``numeric``: small compiled kernels the frame-rate searches share.

Beside them: ``cad`` (the part's CAD model), ``scanplan`` (a part's scan plan), ``types`` (the
data of a pass), ``devices`` (the camera and robot protocols), ``normals``, ``validate`` and
``fileio``. No threads, sockets or global state; it imports no other package of the project.
"""
