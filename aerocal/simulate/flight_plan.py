"""Flight plans: parallel strips at given overlaps, transversal and cross strips, speed and timing.

A plan covers a rectangle of the world frame (easting, northing). Frames are oriented with the image
top towards the flight direction, so the along-track footprint is ``height_px * GSD`` and the
across-track footprint ``width_px * GSD``. The base (distance between exposures) is
``(1 - forward_overlap) * along-track footprint``; the strip spacing ``(1 - side_overlap) *
across-track footprint``, both at the mean terrain height.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from aerocal.camera import Camera
from aerocal.geometry import body_rpy_to_R_cw


@dataclass(frozen=True)
class FlightPlanConfig:
    """A block of parallel strips. Angles in degrees, distances in metres, times in seconds."""

    height_agl_m: float = 850.0  # flying height above the mean terrain
    forward_overlap: float = 0.60
    side_overlap: float = 0.20
    speed_m_s: float = 60.0  # ground speed
    direction: str = "ew"  # main strips along "ew" (east-west) or "ns" (north-south)
    serpentine: bool = True  # alternate flight directions between neighbouring strips
    reverse_first: bool = False  # first strip flown west (ew) or south (ns)
    n_strips: int | None = None  # None: as many as cover the area
    images_per_strip: int | None = None  # None: as many as cover the area (+ extend at each end)
    extend_images: int = 1  # extra exposures beyond each end of a strip
    transversal_strips: int = 0  # strips perpendicular to the main ones, in the middle of the area
    transversal_images: int | None = None
    cross_block: bool = False  # a second full set of strips perpendicular to the first (Mitishita)
    turn_time_s: float = 60.0  # time between the end of a strip and the start of the next
    attitude_jitter_deg: float = 0.5  # std of true roll/pitch about level; yaw about the heading
    height_jitter_m: float = 2.0  # std of true height about the planned altitude
    # wind (east, north) in m/s. Without it (the default) every strip is flown at ``speed_m_s`` over the ground,
    # heading along its track. With it ``speed_m_s`` is the airspeed: the aircraft crabs into the cross wind to keep
    # its track (heading = track + crab angle, the frames turned with it) and its ground speed is the airspeed along
    # the track plus the wind along it, so strips flown against the wind are slower. Measured on the real seneca
    # flight (fixed wing, 2013): ground speeds 5-8 m/s one way and 11-15 m/s the other, heading 2-10 deg off the
    # track; a block flown at one ground speed cannot tell a rolling-shutter readout from an affinity
    wind_m_s: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        if not (self.height_agl_m > 0 and self.speed_m_s > 0):
            raise ValueError("FlightPlanConfig: height_agl_m and speed_m_s must be positive, got "
                             f"{self.height_agl_m}, {self.speed_m_s}")
        if not (0.0 <= self.forward_overlap < 1.0 and 0.0 <= self.side_overlap < 1.0):
            raise ValueError("FlightPlanConfig: forward_overlap and side_overlap must be fractions in [0, 1), got "
                             f"{self.forward_overlap}, {self.side_overlap}")
        if self.direction not in ("ew", "ns"):
            raise ValueError(f"FlightPlanConfig.direction must be 'ew' or 'ns', got {self.direction!r}")
        for name in ("n_strips", "images_per_strip", "transversal_images"):
            if getattr(self, name) is not None and getattr(self, name) < 1:
                raise ValueError(f"FlightPlanConfig.{name} must be 1 or more, or None, got {getattr(self, name)}")
        if self.extend_images < 0 or self.transversal_strips < 0 or self.turn_time_s < 0:
            raise ValueError("FlightPlanConfig: extend_images, transversal_strips and turn_time_s must be 0 or more")
        if self.attitude_jitter_deg < 0 or self.height_jitter_m < 0:
            raise ValueError("FlightPlanConfig: attitude_jitter_deg and height_jitter_m must be 0 or more")


@dataclass
class Trajectory:
    """True exposure stations of a flight (arrays of length N)."""

    time_s: np.ndarray  # seconds after the first exposure
    C: np.ndarray  # (N, 3) projection centres, world metres
    R_cw: np.ndarray  # (N, 3, 3) world-to-camera
    velocity: np.ndarray  # (N, 3) m/s
    heading_deg: np.ndarray  # planned track, clockwise from north (the aircraft's heading crabs off it in a wind)
    strip: np.ndarray  # strip index (transversal strips numbered after the main ones)
    transversal: np.ndarray  # bool: part of a transversal/cross strip
    gsd_m: float
    base_m: float
    spacing_m: float

    def __len__(self) -> int:
        return len(self.time_s)

    def subset(self, idx: np.ndarray) -> Trajectory:
        return Trajectory(
            self.time_s[idx], self.C[idx], self.R_cw[idx], self.velocity[idx], self.heading_deg[idx],
            self.strip[idx], self.transversal[idx], self.gsd_m, self.base_m, self.spacing_m,
        )


def footprint_m(camera: Camera, height_agl_m: float) -> tuple[float, float, float]:
    """(GSD, across-track footprint, along-track footprint) in metres for a nadir frame."""
    gsd = height_agl_m / camera.f
    return gsd, camera.width * gsd, camera.height * gsd


def _strip_lines(lo: float, hi: float, spacing: float, n: int | None) -> np.ndarray:
    if n is None:
        n = max(1, math.ceil((hi - lo) / spacing) + 1)
    centre = 0.5 * (lo + hi)
    return centre + (np.arange(n) - (n - 1) / 2.0) * spacing


def _stations(lo: float, hi: float, base: float, n: int | None, extend: int) -> np.ndarray:
    if n is None:
        n = max(2, math.ceil((hi - lo) / base) + 1 + 2 * extend)
    centre = 0.5 * (lo + hi)
    return centre + (np.arange(n) - (n - 1) / 2.0) * base


def plan_flight(
    config: FlightPlanConfig,
    camera: Camera,
    bounds: tuple[float, float, float, float],
    terrain_height_m: float,
    rng: np.random.Generator,
) -> Trajectory:
    """Plan the strips over ``bounds`` = (e_min, n_min, e_max, n_max) and fly them (true stations)."""
    gsd, across, along = footprint_m(camera, config.height_agl_m)
    base = (1.0 - config.forward_overlap) * along
    spacing = (1.0 - config.side_overlap) * across
    e0, n0, e1, n1 = bounds
    altitude = terrain_height_m + config.height_agl_m

    segments: list[tuple[np.ndarray, np.ndarray, float, int, bool]] = []  # (e, n, heading, strip, transv.)

    def add_block(direction: str, n_strips: int | None, n_images: int | None, first_reverse: bool,
                  transversal: bool) -> None:
        if direction == "ew":
            lines = _strip_lines(n0, n1, spacing, n_strips)
            along_pos = _stations(e0, e1, base, n_images, config.extend_images)
        else:
            lines = _strip_lines(e0, e1, spacing, n_strips)
            along_pos = _stations(n0, n1, base, n_images, config.extend_images)
        for i, line in enumerate(lines):
            reverse = first_reverse ^ (config.serpentine and i % 2 == 1)
            pos = along_pos[::-1] if reverse else along_pos
            if direction == "ew":
                heading = 270.0 if reverse else 90.0
                e, n = pos, np.full_like(pos, line)
            else:
                heading = 180.0 if reverse else 0.0
                e, n = np.full_like(pos, line), pos
            segments.append((e, n, heading, len(segments), transversal))

    add_block(config.direction, config.n_strips, config.images_per_strip, config.reverse_first, False)
    other = "ns" if config.direction == "ew" else "ew"
    if config.cross_block:
        add_block(other, config.n_strips, config.images_per_strip, config.reverse_first, True)
    if config.transversal_strips:
        add_block(other, config.transversal_strips, config.transversal_images, False, True)

    times, es, ns, headings, crabs, speeds, strips, transv = [], [], [], [], [], [], [], []
    t = 0.0
    for e, n, track, strip, is_t in segments:
        k = len(e)
        crab, ground_speed = wind_triangle(track, config.speed_m_s, config.wind_m_s)
        times.append(t + np.arange(k) * base / ground_speed)
        t = times[-1][-1] + config.turn_time_s
        es.append(e)
        ns.append(n)
        headings.append(np.full(k, track))
        crabs.append(np.full(k, crab))
        speeds.append(np.full(k, ground_speed))
        strips.append(np.full(k, strip))
        transv.append(np.full(k, is_t))
    time_s = np.concatenate(times)
    heading = np.concatenate(headings)
    N = len(time_s)
    C = np.column_stack([np.concatenate(es), np.concatenate(ns), np.full(N, altitude)])
    C[:, 2] += rng.normal(0.0, config.height_jitter_m, N)
    tr = np.radians(heading)
    velocity = np.concatenate(speeds)[:, None] * np.column_stack([np.sin(tr), np.cos(tr), np.zeros(N)])
    jitter = rng.normal(0.0, config.attitude_jitter_deg, (N, 3))
    yaw = heading + np.concatenate(crabs)  # the aircraft points into the cross wind, the frames with it
    R = np.stack([body_rpy_to_R_cw(j[0], j[1], h + j[2]) for j, h in zip(jitter, yaw, strict=True)])
    return Trajectory(
        time_s=time_s, C=C, R_cw=R, velocity=velocity, heading_deg=heading,
        strip=np.concatenate(strips).astype(np.int32), transversal=np.concatenate(transv),
        gsd_m=gsd, base_m=base, spacing_m=spacing,
    )


def wind_triangle(track_deg: float, airspeed_m_s: float, wind_m_s: tuple[float, float]) -> tuple[float, float]:
    """The crab angle (degrees, heading minus track, clockwise) and the ground speed (m/s) of an aircraft keeping
    the track ``track_deg`` (clockwise from north) at ``airspeed_m_s`` in the wind ``wind_m_s`` (east, north).

    Raises:
        ValueError: the cross wind is at least ``airspeed_m_s``, or the head wind leaves no positive ground speed.
    """
    t = math.radians(track_deg)
    along = (math.sin(t), math.cos(t))
    right = (math.cos(t), -math.sin(t))
    w_along = wind_m_s[0] * along[0] + wind_m_s[1] * along[1]
    w_cross = wind_m_s[0] * right[0] + wind_m_s[1] * right[1]
    if abs(w_cross) >= airspeed_m_s:
        raise ValueError(f"a cross wind of {abs(w_cross):.3g} m/s is not flown at an airspeed of "
                         f"{airspeed_m_s:.3g} m/s")
    air_along = math.sqrt(airspeed_m_s**2 - w_cross**2)
    ground = air_along + w_along
    if ground <= 0:
        raise ValueError(f"a head wind of {-w_along:.3g} m/s stops an aircraft flying {airspeed_m_s:.3g} m/s on "
                         f"a track of {track_deg:g} deg")
    return math.degrees(math.atan2(-w_cross, air_along)), ground


def overlaps(traj: Trajectory, camera: Camera, height_agl_m: float) -> tuple[float, float]:
    """Mean forward and side overlap (fractions) measured from the true stations of the main strips.

    Forward: 1 - (median distance between consecutive stations of a strip) / along-track footprint.
    Side: 1 - (median distance between neighbouring parallel strip lines) / across-track footprint.
    """
    _, across, along = footprint_m(camera, height_agl_m)
    main = ~traj.transversal
    fwd, lines, dirs = [], [], []
    for s in np.unique(traj.strip[main]):
        sel = traj.strip == s
        c = traj.C[sel, :2]
        fwd.append(np.median(np.linalg.norm(np.diff(c, axis=0), axis=1)))
        h = traj.heading_deg[sel][0]
        ew = h in (90.0, 270.0)
        lines.append(np.median(c[:, 1] if ew else c[:, 0]))
        dirs.append(ew)
    forward = 1.0 - float(np.median(fwd)) / along
    lines_arr = np.sort(np.asarray(lines))
    side = 1.0 - float(np.median(np.diff(lines_arr))) / across if len(lines_arr) > 1 else float("nan")
    return forward, side
