"""What a fingertip sensor publishes for two parallel objects pressed into its gel side by side, as
the grasp lays them (`tensortouch grasp --perception`).

The grasp's sensor physics (dome_contact) renders the gel under two objects of one diameter, laid
across the finger `gap_mm` apart (the grasp scene's free space between them) either side of the
apex, each pressed `depth_mm` into the gel; the frames go through the runtime's pipeline
(`open_pipeline`: startup baseline, the package's network and contact stage). Per diameter and depth:
the clusters it publishes and their total force. The grasp's controller can only tell apart what is
published, so a diameter that gives no cluster is one the grasp cannot see.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .dome_contact import ObjectContact
from .sensor_mount import SensorMount


@dataclass(frozen=True)
class PerceptionConfig:
    diameters_mm: tuple = (1.0, 1.5, 2.0, 3.0, 6.0, 8.0)    # the randomized task's cables 1-3 mm, pens 6-10 mm
    depths_mm: tuple = (0.25, 0.5, 1.0)                    # the grasp's gel takes up to 1.2 mm (its cushion)
    gap_mm: float = 5.0                                    # grasp SceneConfig.gap_mm: free space between them
    rest_frames: int = 40                                  # the runtime's startup baseline, and more
    pressed_frames: int = 3                                # the last one is reported

    def __post_init__(self):
        for name in ("diameters_mm", "depths_mm"):
            v = getattr(self, name)
            if not v or any(not (x > 0) for x in v):
                raise ValueError(f"PerceptionConfig.{name}: expected positive numbers, got {v!r}")


def pair_contacts(mount: SensorMount, diameter_mm: float, depth_mm: float, gap_mm: float) -> list[ObjectContact]:
    """Two parallel objects of `diameter_mm` lying across the finger (along the sensor's y axis), their
    axes (diameter + gap) apart and centred on the apex, each `depth_mm` into a fingertip of radius
    `mount.tip_radius_mm`: seen from the fingertip centre an axis x mm across lies at θ = atan(x / (R + r))
    from the pad axis, towards ±sensor x. Sensor frame, no shear."""
    if diameter_mm <= 0 or depth_mm <= 0 or gap_mm < 0:
        raise ValueError(f"pair_contacts: expected diameter > 0, depth > 0, gap >= 0 (mm), got "
                         f"{diameter_mm}, {depth_mm}, {gap_mm}")
    r = diameter_mm / 2.0
    half = (diameter_mm + gap_mm) / 2.0
    out = []
    for k, x in enumerate((-half, half)):
        th = np.arctan2(x, mount.tip_radius_mm + r)
        u_sensor = np.array([np.sin(th), 0.0, np.cos(th)])
        point = mount.direction_to_gel(mount.R_ts @ u_sensor)
        out.append(ObjectContact(point, np.array([0.0, 1.0, 0.0]), r, float(depth_mm), np.zeros(3), k))
    return out


@dataclass
class Response:
    diameter_mm: float
    depth_mm: float
    clusters: list            # (position mm, |F| N) per published cluster
    total_n: float            # |sum of the clusters' forces|


def respond(package, calibration, unit, objects: list[ObjectContact], cfg: PerceptionConfig,
            sensor_id: str) -> tuple[list, float]:
    """The clusters (position mm, |F| N) the runtime publishes for the gel pressed by `objects`, and
    their total |F|, after `cfg.rest_frames` untouched frames."""
    from ...runtime.pipeline import open_pipeline
    from .sim_sensor import gel_frame

    pipe = open_pipeline(package, calibration, sensor_id=sensor_id)
    rng = np.random.default_rng(0)
    t = 0.0
    for _ in range(cfg.rest_frames):
        pipe.process(gel_frame(unit, [], rng), t)
        t += 0.04
    res = None
    for _ in range(cfg.pressed_frames):
        res = pipe.process(gel_frame(unit, objects, rng), t)
        t += 0.04
    clusters = [(np.round(np.asarray(c.position_mm, float), 2).tolist(), float(np.linalg.norm(c.force_n)))
                for c in res.clusters]
    return clusters, float(np.linalg.norm(res.force_n))


def run(package, calibration, unit, cfg: PerceptionConfig, sensor_id: str,
        mount: SensorMount | None = None) -> list[Response]:
    mount = mount or SensorMount()
    out = []
    for d in cfg.diameters_mm:
        for z in cfg.depths_mm:
            cl, total = respond(package, calibration, unit, pair_contacts(mount, d, z, cfg.gap_mm), cfg, sensor_id)
            out.append(Response(float(d), float(z), cl, total))
    return out


def table(rows: list[Response], model: str) -> str:
    """Markdown: per diameter and depth the clusters published (two objects pressed) and their force."""
    lines = [(f"What `{model}` publishes for two parallel objects pressed side by side (`tensortouch grasp "
              "--perception`):"), "",
             "| diameter (mm) | depth (mm) | clusters | total \\|F\\| (N) | each cluster \\|F\\| (N) |",
             "|---|---|---|---|---|"]
    for r in rows:
        each = ", ".join(f"{f:.2f}" for _, f in r.clusters) or "—"
        lines.append(f"| {r.diameter_mm:g} | {r.depth_mm:g} | {len(r.clusters)} | {r.total_n:.2f} | {each} |")
    return "\n".join(lines) + "\n"
