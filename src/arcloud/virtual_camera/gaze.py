"""Where a walking user's camera looks: fixations on targets at a bounded turning rate, glances at the
floor and the ceiling, fast turns of the head, and a hand's jitter. Cameras follow OpenCV axes (x right,
y down, z forward) in a z-up world. See ``arcloud.virtual_camera.walk``."""

from __future__ import annotations

import math

import numpy as np

from arcloud.errors import InvalidInput
from arcloud.virtual_camera.path import smooth

UP = np.array([0.0, 0.0, 1.0])
#: Distance per metre of size for a thing to fit in a VGA view (half field of view about 28 degrees).
FIT_PER_SIZE = 0.5 / math.tan(math.radians(28.0))


def look_at(eye: np.ndarray, target: np.ndarray, *, roll_rad: float = 0.0) -> np.ndarray:
    """(4, 4) cam2world of a camera at ``eye`` (3,) whose optical axis (+z) points at ``target`` (3,),
    with image x to the right and image y down relative to the world's +z up; ``roll_rad`` turns the
    image about the optical axis. The view must not be vertical."""
    eye = np.asarray(eye, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, UP)
    norm = np.linalg.norm(right)
    if norm < 1e-6:
        raise InvalidInput("target", "a target not straight above or below the eye", np.array2string(forward))
    right /= norm
    down = np.cross(forward, right)
    if roll_rad:
        c, s = math.cos(roll_rad), math.sin(roll_rad)
        right, down = c * right + s * down, -s * right + c * down
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, down, forward, eye
    return pose


#: Half the field of view (horizontal, vertical) within which a target counts as in view: a VGA
#: camera with fx = fy = 525 px sees about 31 x 25 degrees either side of its axis.
VIEW_HALF_DEG = (28.0, 21.0)


def gaze_angles(
    eyes: np.ndarray,
    targets: np.ndarray,
    extents: np.ndarray,
    rng: np.random.Generator,
    *,
    fixation_frames: int,
    max_turn_deg: float = 4.0,
    max_pitch_deg: float = 2.5,
    pitch_range_deg: tuple[float, float] = (-65.0, 20.0),
) -> tuple[np.ndarray, np.ndarray]:
    """(N,) yaw and (N,) pitch of the view, in radians: the head fixates one target at a time,
    turning towards it at most ``max_turn_deg`` (yaw) and ``max_pitch_deg`` per frame. Each next
    target is the one that the turning head would hold in good view (far enough to fit, near enough
    to see) longest over the next fixation, weighed by how little it has been in view so far, whether
    it will be in good view again later, and whether this side of it is new."""
    n = len(eyes)
    heading = np.gradient(smooth(eyes[:, :2], 5.0), axis=0) if n > 1 else np.array([[1.0, 0.0]])
    heading_yaw = np.unwrap(np.arctan2(heading[:, 1], heading[:, 0]))
    if len(targets) == 0:  # look ahead, a little down
        return smooth(heading_yaw, 8.0), np.full(n, math.radians(-15.0))
    n_targets = len(targets)
    near = np.maximum(0.7, 0.6 * FIT_PER_SIZE * extents)  # most of it in view
    far = np.maximum(4.5, near + 1.0)
    low, high = np.radians(pitch_range_deg)
    # Per frame and target: direction (yaw, pitch) from the eye, and whether the distance suits.
    delta = targets[None, :, :] - eyes[:, None, :]  # (frames, targets, 3)
    dist = np.linalg.norm(delta, axis=2)
    yaw_to = np.arctan2(delta[..., 1], delta[..., 0])
    pitch_to = np.clip(np.arctan2(delta[..., 2], np.linalg.norm(delta[..., :2], axis=2)), low, high)
    in_range = (dist >= near) & (dist <= far)
    ahead = np.abs((yaw_to - heading_yaw[:, None] + math.pi) % (2 * math.pi) - math.pi) < math.radians(100)
    good = in_range & ahead
    later = np.concatenate([np.cumsum(good[::-1], axis=0)[::-1], np.zeros((1, n_targets))])  # frames i.. in good view
    half_yaw, half_pitch = np.radians(VIEW_HALF_DEG)
    max_turn, max_pitch = math.radians(max_turn_deg), math.radians(max_pitch_deg)

    def follow(k: int, start: int, stop: int, yaw0: float, pitch0: float) -> tuple[np.ndarray, np.ndarray]:
        """The head's yaw and pitch over frames [start, stop) turning from (yaw0, pitch0) to target k."""
        yaws, pitches = np.empty(stop - start), np.empty(stop - start)
        y, p = yaw0, pitch0
        for f in range(start, stop):
            dy = (yaw_to[f, k] - y + math.pi) % (2 * math.pi) - math.pi
            y += min(max(dy, -max_turn), max_turn)
            p += min(max(pitch_to[f, k] - p, -max_pitch), max_pitch)
            yaws[f - start], pitches[f - start] = y, p
        return yaws, pitches

    def in_view(frames: np.ndarray, yaws: np.ndarray, pitches: np.ndarray) -> np.ndarray:
        """(len(frames), targets) whether each target is in view and in range."""
        dy = np.abs((yaw_to[frames] - yaws[:, None] + math.pi) % (2 * math.pi) - math.pi)
        dp = np.abs(pitch_to[frames] - pitches[:, None])
        return (dy * np.cos(pitch_to[frames]) < half_yaw) & (dp < half_pitch) & in_range[frames]

    seen = np.zeros(n_targets)  # frames each target was in view
    sides = np.zeros((n_targets, 8))  # fixations per target and 45-degree side
    yaw, pitch = np.empty(n), np.empty(n)
    # Start facing what is in range now but rarely ahead later (the user may start facing anywhere).
    first = int(np.argmax(in_range[0] * (1.0 + fixation_frames / (later[0] + fixation_frames)) + 0.1 * rng.random(n_targets)))
    y0, p0 = float(yaw_to[0, first]), float(pitch_to[0, first])
    i, previous = 0, -1
    while i < n:
        hold = int(rng.integers(max(1, fixation_frames * 2 // 3), fixation_frames * 4 // 3 + 1))
        # Each candidate: turn towards it (up to another ``hold`` frames), then hold it ``hold`` frames.
        horizon = min(2 * hold, n - i)
        frames = np.arange(i, i + horizon)
        plans, spans, quality = [], [], np.zeros(n_targets)
        for k in range(n_targets):
            plan = follow(k, i, i + horizon, y0, p0)
            visible = in_view(frames, *plan)[:, k]
            start = int(np.argmax(visible)) if visible.any() else horizon
            span = min(horizon, start + hold) if visible.any() else min(hold, horizon)
            plans.append(plan)
            spans.append(span)
            quality[k] = visible[:span].mean()  # share of the time spent with it in view
        scarce = fixation_frames / (later[min(i + horizon, n)] + fixation_frames)  # 1 when never in good view again
        deficit = 1.0 / (1.0 + seen / fixation_frames)
        side = ((yaw_to[i + horizon // 2] + 2 * math.pi) / (2 * math.pi) * 8).astype(int) % 8
        novelty = 1.0 / (1.0 + sides[np.arange(n_targets), side])
        score = (
            4.0 * quality * (0.25 + deficit)
            + 1.0 * deficit * (quality > 0)
            + 2.0 * quality * scarce * deficit
            + 2.0 * novelty * quality
            - 0.8 * (np.arange(n_targets) == previous)
            + 0.3 * rng.random(n_targets)
        )
        k = int(np.argmax(score))
        span = spans[k]
        frames = frames[:span]
        yaw[frames], pitch[frames] = plans[k][0][:span], plans[k][1][:span]
        visible = in_view(frames, yaw[frames], pitch[frames])
        seen += visible.sum(axis=0)
        shown = visible.any(axis=0)
        sides[shown, side[shown]] += 1
        y0, p0, previous = float(yaw[frames[-1]]), float(pitch[frames[-1]]), k
        i += span
    # Repair: a target barely seen gets the stretch of the walk where it is longest in good view,
    # unless that stretch is where the only view of another target is; the head follows the rate limits.
    wanted_yaw, wanted_pitch = np.unwrap(yaw), pitch.copy()
    owner = np.full(n, -1)
    length = min(fixation_frames + 10, n)
    for j in np.argsort(seen):
        if seen[j] >= fixation_frames / 2 or length < 1:
            continue
        counts = np.convolve(good[:, j].astype(float), np.ones(length), mode="valid")
        counts[np.convolve((owner >= 0).astype(float), np.ones(length), mode="valid") > 0] = -1  # one repair per stretch
        a = int(np.argmax(counts))
        if counts[a] < length / 2:
            continue
        stretch = np.arange(a, a + length)
        wanted_yaw[stretch] = wanted_yaw[a] + (yaw_to[stretch, j] - wanted_yaw[a] + math.pi) % (2 * math.pi) - math.pi
        wanted_pitch[stretch] = pitch_to[stretch, j]
        owner[stretch] = j
    if np.any(owner >= 0):
        yaw = _rate_limited(np.unwrap(wanted_yaw), max_turn)
        pitch = _rate_limited(wanted_pitch, max_pitch)
    return smooth(np.unwrap(yaw), 3.0), smooth(pitch, 3.0)


def _rate_limited(wanted: np.ndarray, max_step: float) -> np.ndarray:
    """Follows ``wanted`` (N,) changing by at most ``max_step`` per sample."""
    out = np.empty_like(wanted)
    out[0] = wanted[0]
    for i in range(1, len(wanted)):
        out[i] = out[i - 1] + min(max(wanted[i] - out[i - 1], -max_step), max_step)
    return out


#: Glances: the head pitches to the floor (60 % of glances) or the ceiling at about this rate, holds, comes back.
GLANCE_RATE_DEG = 6.0
GLANCE_FLOOR_DEG, GLANCE_CEILING_DEG = (-80.0, -55.0), (35.0, 65.0)
GLANCE_HOLD_FRAMES = (3, 15)
#: Fast turns: this much yaw at this mean rate (degrees a frame), held, then back.
FAST_TURN_DEG, FAST_TURN_RATE_DEG = (60.0, 150.0), (8.0, 15.0)
FAST_TURN_HOLD_FRAMES = (3, 15)


def _excursion(n: int, start: int, ramp_frames: int, hold_frames: int) -> np.ndarray:
    """(n,) weights in [0, 1]: a raised-cosine rise over ``ramp_frames`` from ``start``, a hold of
    ``hold_frames``, the same fall."""
    t = np.arange(n) - start
    rise = 0.5 - 0.5 * np.cos(np.pi * np.clip(t / ramp_frames, 0.0, 1.0))
    fall = 0.5 - 0.5 * np.cos(np.pi * np.clip((ramp_frames + hold_frames + ramp_frames - t) / ramp_frames, 0.0, 1.0))
    return np.minimum(rise, fall)


def with_glances(pitch: np.ndarray, per_100_frames: float, rng: np.random.Generator) -> np.ndarray:
    """``pitch`` (N,) radians with glances at the floor and the ceiling, one at a time: exponential
    gaps (mean ``100 / per_100_frames`` frames) from the end of one to the start of the next."""
    n = len(pitch)
    out = pitch.copy()
    t = 0.0
    while per_100_frames > 0:
        t += float(rng.exponential(100.0 / per_100_frames))
        if t >= n:
            break
        start, floor, hold = int(t), rng.random() < 0.6, int(rng.integers(GLANCE_HOLD_FRAMES[0], GLANCE_HOLD_FRAMES[1] + 1))
        target = math.radians(float(rng.uniform(*(GLANCE_FLOOR_DEG if floor else GLANCE_CEILING_DEG))))
        ramp = max(2, math.ceil(abs(math.degrees(target - out[start])) / GLANCE_RATE_DEG))
        out = out + _excursion(n, start, ramp, hold) * (target - out)
        t = start + 2 * ramp + hold
    return out


def with_fast_turns(yaw: np.ndarray, per_100_frames: float, rng: np.random.Generator) -> np.ndarray:
    """``yaw`` (N,) radians with fast turns of the head away and back, one at a time (gaps as glances')."""
    n = len(yaw)
    out = yaw.copy()
    t = 0.0
    while per_100_frames > 0:
        t += float(rng.exponential(100.0 / per_100_frames))
        if t >= n:
            break
        start, hold = int(t), int(rng.integers(FAST_TURN_HOLD_FRAMES[0], FAST_TURN_HOLD_FRAMES[1] + 1))
        turn_deg = float(rng.uniform(*FAST_TURN_DEG)) * (1 if rng.random() < 0.5 else -1)
        ramp = max(2, math.ceil(abs(turn_deg) / float(rng.uniform(*FAST_TURN_RATE_DEG))))
        out = out + math.radians(turn_deg) * _excursion(n, start, ramp, hold)
        t = start + 2 * ramp + hold
    return out


def with_jitter(poses: list[np.ndarray], jitter_deg: float, jitter_m: float, rng: np.random.Generator) -> list[np.ndarray]:
    """Each (4, 4) cam2world pose times a small rigid motion in its camera frame: rotation and
    translation noise with standard deviations ``jitter_deg`` and ``jitter_m`` per axis, smoothed
    over about a frame (a hand's tremor)."""
    from scipy.spatial.transform import Rotation

    n = len(poses)
    if n == 0 or (jitter_deg == 0 and jitter_m == 0):
        return poses
    sigma_frames = 1.0
    gain = math.sqrt(2 * math.sqrt(math.pi) * sigma_frames)  # smoothing shrinks white noise by this much
    angles = smooth(rng.normal(0.0, math.radians(jitter_deg), (n, 3)), sigma_frames) * gain
    offsets = smooth(rng.normal(0.0, jitter_m, (n, 3)), sigma_frames) * gain
    motion = np.tile(np.eye(4), (n, 1, 1))
    motion[:, :3, :3] = Rotation.from_rotvec(angles).as_matrix()
    motion[:, :3, 3] = offsets
    return [pose @ m for pose, m in zip(poses, motion)]
