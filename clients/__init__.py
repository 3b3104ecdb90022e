"""What a robot cell controller or a cloud subscriber imports to use the flyscan service.

- :class:`FlyscanClient`: the REST API (arm a scan, wait for it, fetch its info, pose and clouds,
  manage parts and calibration), errors raised as :class:`FlyscanError` with the service's reason.
- :class:`CloudSubscriber`: the ZeroMQ publisher's clouds, edge clouds, poses and status as
  :class:`Message` objects (JSON header + numpy array), lost messages counted.
- :func:`place_correction`: the TCP place pose that corrects the part's measured misplacement
  (``clients.placement``: frames, units, the equation), and UR pose vector conversions.
- ``python -m clients.cell_controller``: the loop a robot cell runs, as an example program.

Light on purpose: the standard library, numpy, httpx and pyzmq; nothing of the service. The
two sides meet only on the wire formats of docs/service.md and docs/files.md (REST, ZeroMQ, binary PLY).
"""
from .http_client import (BadRequest, Conflict, FlyscanClient, FlyscanError, NotFound, ScanFailed,
                          ServiceUnavailable, ServiceUnreachable, Unauthorized, Unprocessable)
from .placement import (PlaceCorrection, PoseNotActionable, corrected_tcp_place,
                        matrix_to_ur_pose, place_correction, pose_actionable, ur_pose_to_matrix)
from .ply import PlyError, parse_ply, xyz_array
from .subscriber import TOPICS, CloudSubscriber, Message, MessageError, load_message

__all__ = [
    "FlyscanClient", "FlyscanError", "ServiceUnreachable", "BadRequest", "Unauthorized",
    "NotFound", "Conflict", "Unprocessable", "ServiceUnavailable", "ScanFailed",
    "CloudSubscriber", "Message", "MessageError", "load_message", "TOPICS",
    "PlyError", "parse_ply", "xyz_array",
    "place_correction", "corrected_tcp_place", "PlaceCorrection", "PoseNotActionable",
    "pose_actionable", "ur_pose_to_matrix", "matrix_to_ur_pose",
]
