"""The hand: a URDF loaded into Pinocchio, the two fingers used for pinching, and mount variants.

A mount variant moves the thumb's distal joint: its placement in the parent link gets the
z-offset `z_m` (along the parent's z, the finger's long axis) and a pitch about the parent's y axis.
Variants are made by editing `model.jointPlacements` in memory; `write_urdf` writes the chosen one
as a URDF (the joint's <origin> edited, every other line kept).
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path

import numpy as np

from ...contracts.errors import TensorTouchError
from ...contracts.files import atomic_write

ALLEGRO_RIGHT = "robots/allegro_hand_description/urdf/allegro_right_hand.urdf"


class HandModelError(TensorTouchError):
    """A hand URDF or finger name is not what was expected."""


@dataclass(frozen=True)
class Finger:
    """One finger: its joints (base to tip), the fingertip frame and the tip sphere radius (m)."""

    joints: tuple[str, ...]
    tip_frame: str
    tip_radius_m: float = 0.012


@dataclass(frozen=True)
class HandSpec:
    """The pinching pair. Defaults: the Allegro right hand's thumb (12-15) and index (0-3)."""

    thumb: Finger = field(default_factory=lambda: Finger(("joint_12.0", "joint_13.0", "joint_14.0", "joint_15.0"),
                                                         "link_15.0_tip"))
    index: Finger = field(default_factory=lambda: Finger(("joint_0.0", "joint_1.0", "joint_2.0", "joint_3.0"),
                                                         "link_3.0_tip"))

    @property
    def distal_joint(self) -> str:
        """The thumb joint whose placement a mount variant edits."""
        return self.thumb.joints[-1]


def default_urdf() -> Path:
    """The Allegro right hand shipped by the `example-robot-data` wheel (BSD)."""
    try:
        dist = metadata.distribution("example-robot-data")
    except metadata.PackageNotFoundError as exc:
        raise HandModelError("example-robot-data is not installed; install the extra: pip install "
                             "'tensortouch[hand]', or pass --urdf PATH") from exc
    path = Path(dist.locate_file(f"cmeel.prefix/share/example-robot-data/{ALLEGRO_RIGHT}"))
    if not path.is_file():
        raise HandModelError(f"{path}: the Allegro URDF is missing from example-robot-data")
    return path


def load(urdf: str | Path | None = None, spec: HandSpec | None = None):
    """Pinocchio model of `urdf` (default Allegro right hand), checked against `spec`."""
    import pinocchio as pin

    spec = spec or HandSpec()
    path = Path(urdf) if urdf else default_urdf()
    if not path.is_file():
        raise HandModelError(f"{path}: no such URDF file")
    try:
        model = pin.buildModelFromUrdf(str(path))
    except Exception as exc:  # Pinocchio raises plain ValueError/RuntimeError on parse errors
        raise HandModelError(f"{path}: not a URDF Pinocchio can load ({exc})") from exc
    for finger in (spec.thumb, spec.index):
        for j in finger.joints:
            if not model.existJointName(j):
                raise HandModelError(f"{path}: joint {j!r} not found; expected one of {list(model.names)[1:]}")
        if not model.existFrame(finger.tip_frame):
            raise HandModelError(f"{path}: fingertip frame {finger.tip_frame!r} not found")
    return model


def q_indices(model, finger: Finger) -> np.ndarray:
    """Configuration-vector indices of the finger's joints (all 1-DoF revolute)."""
    return np.array([model.joints[model.getJointId(j)].idx_q for j in finger.joints])


def limits(model, finger: Finger) -> tuple[np.ndarray, np.ndarray]:
    idx = q_indices(model, finger)
    return np.asarray(model.lowerPositionLimit)[idx].copy(), np.asarray(model.upperPositionLimit)[idx].copy()


def nominal_placement(model, spec: HandSpec):
    """The distal joint's placement as the URDF has it (a copy)."""
    return model.jointPlacements[model.getJointId(spec.distal_joint)].copy()


def apply_variant(model, spec: HandSpec, nominal, z_m: float, pitch_rad: float) -> None:
    """Set the thumb distal joint placement to the variant (z-offset along and pitch about the
    parent's axes, on top of the URDF's placement), in place."""
    import pinocchio as pin

    M = nominal.copy()
    t = np.array(M.translation)
    t[2] = z_m
    M.translation = t
    M.rotation = np.asarray(nominal.rotation) @ pin.utils.rotate("y", pitch_rad)
    model.jointPlacements[model.getJointId(spec.distal_joint)] = M


def write_urdf(src: str | Path, dst: str | Path, spec: HandSpec, z_m: float, pitch_rad: float) -> Path:
    """Copy URDF `src` to `dst` with the thumb distal joint's <origin> set to the variant
    (xyz z = z_m, rpy pitch += pitch_rad). Written atomically."""
    src, dst = Path(src), Path(dst)
    tree = ET.parse(src)
    joint = next((j for j in tree.getroot().iter("joint") if j.get("name") == spec.distal_joint), None)
    if joint is None:
        raise HandModelError(f"{src}: joint {spec.distal_joint!r} not found")
    origin = joint.find("origin")
    if origin is None:
        origin = ET.SubElement(joint, "origin", {"xyz": "0 0 0", "rpy": "0 0 0"})
    xyz = [float(v) for v in origin.get("xyz", "0 0 0").split()]
    rpy = [float(v) for v in origin.get("rpy", "0 0 0").split()]
    if any(abs(v) > 1e-12 for v in rpy):
        raise HandModelError(f"{src}: joint {spec.distal_joint!r} origin has rpy {rpy}; only an "
                             "unrotated distal joint can be re-pitched here")
    xyz[2] = z_m
    origin.set("xyz", " ".join(f"{v:.6g}" for v in xyz))
    origin.set("rpy", f"0 {pitch_rad:.6g} 0")
    # package:// mesh paths would break once the file moves: point them at the source tree.
    for mesh in tree.getroot().iter("mesh"):
        resolved = resolve_package_path(src, mesh.get("filename", ""))
        if resolved is not None:
            mesh.set("filename", str(resolved))
    return atomic_write(dst, ET.tostring(tree.getroot(), encoding="utf-8", xml_declaration=True))


def resolve_package_path(urdf: Path, filename: str) -> Path | None:
    """`package://PKG/REST` → the file PKG/REST found beside one of the URDF's ancestors."""
    if not filename.startswith("package://"):
        return None
    pkg, _, rest = filename[len("package://"):].partition("/")
    for a in Path(urdf).resolve().parents:
        for cand in (a / rest if a.name == pkg else None, a / pkg / rest):
            if cand is not None and cand.is_file():
                return cand
    return None


