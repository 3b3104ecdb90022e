"""The place correction: where the robot must put its TCP so that the part, held as the scan
measured it, lands where a nominally held part would.

Frames (docs/design.md): {B} the robot base, {T} the TCP (gripper), {P} the part (its CAD
model). ``^A X_C`` is a 4x4 homogeneous transform, millimetres, mapping coordinates in {C} to
coordinates in {A} (the pose of {C} in {A}).

- ``taught_place`` ^B X_T,place: the TCP pose, in the robot base, at which a part held at its
  nominal grasp lands right (the place pose taught on the robot).
- ``pose`` ^T X_P: the part in the TCP, as the scan measured it (the report's ``pose.matrix``).
- ``nominal_grasp`` ^T X_P,nom: the part in the TCP as it should be held (``GET /parts``:
  ``nominal_grasp``).

The corrected place pose puts the part where the nominal one would be::

    ^B X_T,corrected = ^B X_T,place @ ^T X_P,nom @ inv(^T X_P)

so that ``^B X_T,corrected @ ^T X_P == ^B X_T,place @ ^T X_P,nom``. With the misplacement
``M = ^T X_P @ inv(^T X_P,nom)`` (in {T}) this is ``^B X_T,place @ inv(M)``.

A UR robot speaks poses as ``[x, y, z, rx, ry, rz]``: the position in metres and the
orientation as a rotation vector (axis times angle, radians), both in {B};
:func:`ur_pose_to_matrix` and :func:`matrix_to_ur_pose` convert, with the rotation vector done
by Rodrigues' formula in numpy (accurate near 0 and near 180 degrees).

Use :func:`place_correction` with the scan's ``pose`` entry: it refuses (raises
:class:`PoseNotActionable` with the reasons) a refused pose, a missing one, and one the scanner
says not to act on (``act`` false). :func:`corrected_tcp_place` is the bare equation on
matrices, for a pose already judged.

Light on purpose: numpy only.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = ["PlaceCorrection", "PoseNotActionable", "place_correction", "corrected_tcp_place",
           "correction_entry", "pose_actionable", "ur_pose_to_matrix", "matrix_to_ur_pose",
           "rotvec_to_matrix", "matrix_to_rotvec", "rigid_transform", "FRAMES"]

#: What the correction maps between, stated wherever it is handed out.
FRAMES = ("^B X_T: the TCP {T} in the robot base {B}, mm; the corrected place pose = "
          "taught place pose (^B X_T,place) @ nominal grasp (^T X_P,nom) @ inv(measured pose "
          "^T X_P); ur_pose: [x, y, z (m), rx, ry, rz (rotation vector, rad)] in {B}")
#: How far a rotation block may be from orthonormal (max |R^T R - I|, and |det R - 1|): a
#: matrix from the service is exact to about 1e-15; a hand-typed one needs seven decimals.
ORTHONORMAL_TOL = 1e-6
#: UR poses are in metres, flyscan's in millimetres.
MM_PER_M = 1000.0


class PoseNotActionable(ValueError):
    """The scan's pose must not move the robot: refused, missing, or ``act`` false.

    Attributes
    ----------
    reasons : list of str
        Why, as the scanner put it (never empty).
    """

    def __init__(self, reasons):
        self.reasons = [str(r) for r in reasons] or ["no reason given"]
        super().__init__("the pose is not to act on: " + "; ".join(self.reasons))


@dataclass(frozen=True, eq=False)
class PlaceCorrection:
    """The corrected place pose of the TCP, and what it came from.

    Attributes
    ----------
    tcp_place_mm : (4, 4) float64
        ^B X_T,corrected, mm: move the TCP here to place the part.
    ur_pose : (6,) float64
        The same as a UR pose: [x, y, z] m, [rx, ry, rz] rotation vector rad, in {B}.
    taught_place_mm : (4, 4) float64
        ^B X_T,place, mm, as given.
    misplacement : (4, 4) float64
        ``pose @ inv(nominal_grasp)``, mm, in {T}: how the part sits off its nominal grasp.
    """

    tcp_place_mm: np.ndarray
    ur_pose: np.ndarray
    taught_place_mm: np.ndarray
    misplacement: np.ndarray = field(repr=False)
    frames: str = FRAMES

    def to_dict(self) -> dict:
        """JSON-safe: the service's ``correction`` entry (``act`` true)."""
        return {"act": True, "reasons": [],
                "tcp_place_mm": self.tcp_place_mm.tolist(),
                "ur_pose": self.ur_pose.tolist(),
                "taught_place_mm": self.taught_place_mm.tolist(),
                "frames": self.frames}


def place_correction(taught_place, pose, nominal_grasp) -> PlaceCorrection:
    """The TCP place pose that corrects the measured misplacement, from the scan's pose entry.

    Parameters
    ----------
    taught_place : (4, 4) array_like
        ^B X_T,place, mm: the TCP pose in the robot base at which a nominally held part lands
        right. A UR pose vector (m, rad) converts with :func:`ur_pose_to_matrix` first.
    pose : dict
        The scan's ``pose`` entry (``GET /scans/{id}``, ``report.json``): ``matrix`` is ^T X_P
        in mm, ``act`` says whether a robot may apply it.
    nominal_grasp : (4, 4) array_like
        ^T X_P,nom, mm: the part's nominal grasp (``GET /parts``: ``nominal_grasp``).

    Returns
    -------
    PlaceCorrection
        ``tcp_place_mm`` = taught_place @ nominal_grasp @ inv(pose["matrix"]), and as a UR pose.

    Raises
    ------
    PoseNotActionable
        The pose is missing (None), refused (``{"refused": reason}``), or not to act on
        (``act`` false: ``reasons`` are its ``act_reasons``).
    ValueError
        A matrix is not a rigid 4x4 transform (the message names it).
    """
    act, reasons = pose_actionable(pose)
    if not act:
        raise PoseNotActionable(reasons)
    taught = _rigid(taught_place, "taught_place")
    measured = _rigid(pose["matrix"], "pose['matrix']")
    nominal = _rigid(nominal_grasp, "nominal_grasp")
    corrected = _corrected(taught, measured, nominal)
    return PlaceCorrection(tcp_place_mm=corrected, ur_pose=matrix_to_ur_pose(corrected),
                           taught_place_mm=taught,
                           misplacement=measured @ _inverse(nominal))


def corrected_tcp_place(taught_place, pose_matrix, nominal_grasp) -> np.ndarray:
    """The bare equation: ^B X_T,place @ ^T X_P,nom @ inv(^T X_P), for a pose already judged.

    Parameters
    ----------
    taught_place : (4, 4) array_like
        ^B X_T,place, mm.
    pose_matrix : (4, 4) array_like
        ^T X_P, mm: the measured pose (``pose["matrix"]``). Whether to act on it is for the
        caller to decide (:func:`place_correction` decides by the pose's ``act``).
    nominal_grasp : (4, 4) array_like
        ^T X_P,nom, mm.

    Returns
    -------
    (4, 4) float64
        ^B X_T,corrected, mm.
    """
    return _corrected(_rigid(taught_place, "taught_place"), _rigid(pose_matrix, "pose_matrix"),
                      _rigid(nominal_grasp, "nominal_grasp"))


def correction_entry(taught_place, pose, nominal_grasp) -> dict:
    """The ``correction`` entry of a scan's info: the move when the pose is to act on, else
    no move (``tcp_place_mm`` and ``ur_pose`` None) and the reasons.

    Parameters as :func:`place_correction`; ``pose`` may be None (no pose). A pose matrix or
    nominal grasp that is not a rigid transform is a reason not to act; a `taught_place` that
    is not one raises ValueError.
    """
    taught = _rigid(taught_place, "taught_place")
    try:
        return place_correction(taught, pose, nominal_grasp).to_dict()
    except PoseNotActionable as exc:
        reasons = exc.reasons
    except ValueError as exc:
        reasons = [f"no correction: {exc}"]
    return {"act": False, "reasons": reasons, "tcp_place_mm": None, "ur_pose": None,
            "taught_place_mm": taught.tolist(), "frames": FRAMES}


def pose_actionable(pose) -> tuple[bool, list[str]]:
    """Whether a robot may act on the scan's ``pose`` entry, and why not.

    ``(act, reasons)``: ``act`` is the pose's own ``act``; a pose without one (a service older
    than ``act``) is to act on only when it is observable and has no flags. None, a refusal
    (``{"refused": reason}``) and an entry without a matrix are not.
    """
    if pose is None:
        return False, ["no pose: the scan has none (no part, or the scan failed)"]
    if not isinstance(pose, dict):
        raise TypeError(f"`pose` must be the scan's pose entry (a dict or None), got "
                        f"{type(pose).__name__}")
    if "refused" in pose:
        return False, [f"no pose: {pose['refused']}"]
    if pose.get("matrix") is None:
        return False, ["no pose: the entry has no matrix"]
    if "act" in pose:
        reasons = [str(r) for r in pose.get("act_reasons") or ()]
        if pose["act"] is True:
            return True, []
        return False, reasons or ["the scanner says not to act on this pose"]
    reasons = [str(f) for f in pose.get("flags") or ()]
    if pose.get("observable") is not True and not reasons:
        reasons = ["not observable: " + (", ".join(a.get("label", a.get("kind", "?"))
                                                   for a in pose.get("free_axes") or ())
                                         or "the scan does not constrain the pose")]
    return not reasons, reasons


# -- UR poses and rotation vectors ------------------------------------------------------------

def ur_pose_to_matrix(ur_pose) -> np.ndarray:
    """A UR pose ``[x, y, z, rx, ry, rz]`` (m; rotation vector, rad) -> (4, 4) float64, mm.

    ValueError unless six finite numbers.
    """
    v = np.asarray(ur_pose, dtype=np.float64)
    if v.shape != (6,) or not np.all(np.isfinite(v)):
        raise ValueError(f"a UR pose must be six finite numbers [x, y, z (m), rx, ry, rz (rad)], "
                         f"got {np.asarray(ur_pose).tolist()!r}")
    m = np.eye(4)
    m[:3, :3] = rotvec_to_matrix(v[3:])
    m[:3, 3] = v[:3] * MM_PER_M
    return m


def matrix_to_ur_pose(matrix) -> np.ndarray:
    """(4, 4) rigid transform, mm -> a UR pose (6,) float64: [x, y, z] m, rotation vector rad
    (angle in [0, pi]). ValueError unless a rigid transform."""
    m = _rigid(matrix, "matrix")
    return np.concatenate([m[:3, 3] / MM_PER_M, matrix_to_rotvec(m[:3, :3])])


def rotvec_to_matrix(rotvec) -> np.ndarray:
    """Rotation vector (3,) (axis times angle, rad) -> rotation matrix (3, 3) float64.

    Rodrigues: R = I + a K + b K^2 with K the cross-product matrix of the vector,
    a = sin(t)/t and b = (1 - cos(t))/t^2, t the angle; near t = 0 by their Taylor series.
    """
    r = np.asarray(rotvec, dtype=np.float64)
    if r.shape != (3,) or not np.all(np.isfinite(r)):
        raise ValueError(f"a rotation vector must be three finite numbers, got {r.tolist()!r}")
    t2 = float(r @ r)
    t = math.sqrt(t2)
    if t < _SMALL_ANGLE:  # series: error below t^4/120 ~ 1e-18
        a = 1.0 - t2 / 6.0
        b = 0.5 - t2 / 24.0
    else:
        a = math.sin(t) / t
        b = (1.0 - math.cos(t)) / t2
    k = np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
    return np.eye(3) + a * k + b * (k @ k)


def matrix_to_rotvec(rotation) -> np.ndarray:
    """Rotation matrix (3, 3) -> rotation vector (3,) float64, rad, angle in [0, pi].

    Through the unit quaternion (Shepperd's choice of its largest component, so accurate for
    every angle, 180 degrees included), its scalar part made >= 0; then
    vector = q_xyz * 2 atan2(|q_xyz|, q_w) / |q_xyz|. At exactly 180 degrees r and -r are the
    same rotation; either may come out.
    """
    rm = np.asarray(rotation, dtype=np.float64)
    if rm.shape != (3, 3) or not np.all(np.isfinite(rm)):
        raise ValueError(f"a rotation matrix must be 3x3 finite, got shape {rm.shape}")
    q = _quaternion(rm)
    if q[0] < 0:
        q = -q
    n = math.hypot(q[1], q[2], q[3])  # scaled: no underflow of the squares
    if n == 0.0:
        return np.zeros(3)
    # atan2 is exact to rounding for a tiny n: the scale tends to 2 / q_w with no cancellation.
    return q[1:] * (2.0 * math.atan2(n, q[0]) / n)


# Below this angle (rad) Rodrigues' coefficients are taken from their series.
_SMALL_ANGLE = 1e-4


def _quaternion(rm: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a rotation matrix, by Shepperd's method (normalised)."""
    trace = rm[0, 0] + rm[1, 1] + rm[2, 2]
    choice = int(np.argmax([trace, rm[0, 0], rm[1, 1], rm[2, 2]]))
    q = np.empty(4)
    if choice == 0:
        s = 2.0 * math.sqrt(max(1.0 + trace, 0.0))
        q[:] = (0.25 * s, (rm[2, 1] - rm[1, 2]) / s, (rm[0, 2] - rm[2, 0]) / s,
                (rm[1, 0] - rm[0, 1]) / s)
    else:
        i = choice - 1
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1.0 + rm[i, i] - rm[j, j] - rm[k, k], 0.0))
        q[0] = (rm[k, j] - rm[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (rm[j, i] + rm[i, j]) / s
        q[1 + k] = (rm[k, i] + rm[i, k]) / s
    return q / np.linalg.norm(q)


# -- helpers ---------------------------------------------------------------------------------

def _corrected(taught: np.ndarray, measured: np.ndarray, nominal: np.ndarray) -> np.ndarray:
    out = taught @ nominal @ _inverse(measured)
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def _inverse(m: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform: [R^T, -R^T t]."""
    out = np.eye(4)
    out[:3, :3] = m[:3, :3].T
    out[:3, 3] = -m[:3, :3].T @ m[:3, 3]
    return out


def rigid_transform(matrix, name: str = "matrix") -> np.ndarray:
    """`matrix` as a (4, 4) float64 rigid transform (mm); ValueError naming it (`name`)
    unless finite, last row [0, 0, 0, 1], and its rotation block orthonormal with determinant
    +1 within `ORTHONORMAL_TOL`."""
    return _rigid(matrix, name)


def _rigid(matrix, name: str) -> np.ndarray:
    """`matrix` as a (4, 4) float64 rigid transform; ValueError naming it otherwise."""
    try:
        m = np.array(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"`{name}` must be a 4x4 rigid transform (mm), got {matrix!r}") from None
    if m.shape != (4, 4):
        hint = (" (a UR pose vector? convert it with ur_pose_to_matrix)" if m.shape == (6,)
                else "")
        raise ValueError(f"`{name}` must be a 4x4 rigid transform (mm), got shape "
                         f"{m.shape}{hint}")
    if not np.all(np.isfinite(m)):
        raise ValueError(f"`{name}` must be finite, got {m.tolist()}")
    if not np.array_equal(m[3], [0.0, 0.0, 0.0, 1.0]):
        raise ValueError(f"`{name}`'s last row must be [0, 0, 0, 1], got {m[3].tolist()}")
    r = m[:3, :3]
    off = float(np.max(np.abs(r.T @ r - np.eye(3))))
    det = float(np.linalg.det(r))
    if off > ORTHONORMAL_TOL or abs(det - 1.0) > ORTHONORMAL_TOL:
        raise ValueError(f"`{name}`'s rotation block must be orthonormal with determinant +1 "
                         f"(within {ORTHONORMAL_TOL:g}), got max|R^T R - I| = {off:.3g}, "
                         f"det = {det:.9g}")
    return m
