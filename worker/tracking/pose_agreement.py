"""How well given poses agree with the images: the three-view reprojection error, against what the images allow.

Corners of a frame a, followed frame by frame (pyramidal Lucas-Kanade, each step checked by tracking back) into two
later frames b and c, are triangulated from a and b with the given poses and projected into c with c's given pose:
the median distance to where they were tracked is `given_px`. The same tracks with poses fitted to them from the
images alone (the essential matrix for a -> b, PnP for c) leave `fitted_px`: what three frames of visual odometry
would achieve on them. Only tracks with parallax once the fitted rotation is taken out count. The ratio
given / fitted is free of scale and resolution: below 1 for exact poses (they carry no noise, the fit does: ICL
0.67-0.72 at 320x240), above it where the steps between the poses disagree with the images (KITTI's GPS/IMU poses
over its first 18 frames: 2.8 at 620x188). Multi-view stereo and the map built on such poses inherit the
disagreement (`bench/RESULTS.md`, issue 21 point 1).

`PoseAgreement` judges a stream from its first frames (`worker.tracking.pose_choice`); `sequence_errors` measures
triples spread over a recorded sequence (`python -m bench pose_consistency`); both through `TripleTracker`.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

MAX_CORNERS = 1500
MIN_POINTS = 20  # points with parallax a triple needs to count
MIN_FLOW_PX = 1.5  # a point's motion from a to b below this gives no parallax to triangulate from
FB_MAX_PX = 0.5  # a corner tracked one frame ahead and back must come back this close
LK_PARAMS = {"winSize": (21, 21), "maxLevel": 3}  # OpenCV's defaults, named


@dataclass(frozen=True)
class TripleError:
    """One triple's median reprojection errors in its third view (pixels): with the given pose, with a fitted one;
    `depth`: the median depth of its points in its first view, triangulated with the given poses (pose units)."""

    given_px: float
    fitted_px: float
    points: int
    depth: float = float("nan")


@dataclass(frozen=True)
class AgreementVerdict:
    """Whether given poses agree with the images: medians over the triples measured and their ratio."""

    given_px: float
    fitted_px: float
    triples: int
    max_ratio: float

    @property
    def ratio(self) -> float:
        return self.given_px / max(self.fitted_px, 1e-6)

    @property
    def agree(self) -> bool:
        return self.ratio <= self.max_ratio

    def to_dict(self) -> dict[str, float | int | bool]:
        return {"reprojection_px": round(self.given_px, 3), "fitted_px": round(self.fitted_px, 3),
                "ratio": round(self.ratio, 2), "max_ratio": self.max_ratio, "triples": self.triples,
                "agree": self.agree}


def grey(image: np.ndarray) -> np.ndarray:
    """An RGB uint8 image (or a grey one) as grey uint8."""
    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)


def _corners(image: np.ndarray) -> np.ndarray | None:
    """Corners to follow in a grey image ([n, 1, 2] float32, sub-pixel), None with fewer than MIN_POINTS."""
    corners = cv2.goodFeaturesToTrack(image, MAX_CORNERS, 0.01, 5)
    if corners is None or len(corners) < MIN_POINTS:
        return None
    return cv2.cornerSubPix(image, corners.astype(np.float32), (3, 3), (-1, -1),
                            (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 20, 0.01))


@dataclass
class _OpenTriple:
    """A triple whose last frame has not come yet: its corners where they started, in its middle frame and now."""

    start: np.ndarray
    poses: list[np.ndarray]
    current: np.ndarray
    kept: np.ndarray
    frames: int = 1
    middle: np.ndarray | None = None


class TripleTracker:
    """Frame triples (a, a + step, a + 2 step) of a stream, one starting every `every` frames (0: at the first frame
    only). The corners of a are followed frame by frame (pyramidal Lucas-Kanade, each step checked by tracking back:
    a corner that does not come back within FB_MAX_PX is dropped), the open triples' corners in one call a frame."""

    def __init__(self, step: int, every: int = 0) -> None:
        self.step, self.every = step, every
        self.previous: np.ndarray | None = None
        self.open: list[_OpenTriple] = []
        self.count = 0

    def add(self, image: np.ndarray, pose_c2w: np.ndarray, K: np.ndarray) -> list[TripleError]:
        """Take the next frame (grey, its pose, the camera); returns the errors of the triples it completes."""
        pose = np.asarray(pose_c2w, np.float64)
        completed = []
        if self.open:
            self._follow(image)
            for triple in self.open:
                triple.frames += 1
                if triple.frames == self.step + 1:
                    triple.middle = triple.current.copy()
                    triple.poses.append(pose)
            for triple in [t for t in self.open if t.frames == 2 * self.step + 1]:
                self.open.remove(triple)
                completed.append(triple_error(triple.start[triple.kept, 0], triple.middle[triple.kept, 0],
                                              triple.current[triple.kept, 0], (*triple.poses, pose), K))
        if self.count == 0 or (self.every and self.count % self.every == 0):
            corners = _corners(image)
            if corners is not None:
                self.open.append(_OpenTriple(corners, [pose], corners.copy(), np.ones(len(corners), bool)))
        self.previous = image
        self.count += 1
        return [e for e in completed if e is not None]

    def _follow(self, image: np.ndarray) -> None:
        current = np.concatenate([t.current for t in self.open])
        ahead, found, _ = cv2.calcOpticalFlowPyrLK(self.previous, image, current, None, **LK_PARAMS)
        back, returned, _ = cv2.calcOpticalFlowPyrLK(image, self.previous, ahead, None, **LK_PARAMS)
        ok = (found.ravel() == 1) & (returned.ravel() == 1)
        ok &= np.linalg.norm((back - current)[:, 0], axis=1) < FB_MAX_PX
        first = 0
        for triple in self.open:
            last = first + len(triple.current)
            triple.current, triple.kept = ahead[first:last], triple.kept & ok[first:last]
            first = last

    def reset(self) -> None:
        """A gap in the stream: the open triples are dropped, the next frame starts one."""
        self.previous, self.open, self.count = None, [], 0


def triple_error(x0: np.ndarray, x1: np.ndarray, x2: np.ndarray,
                 poses_c2w: tuple[np.ndarray, np.ndarray, np.ndarray], K: np.ndarray) -> TripleError | None:
    """The reprojection errors of a triple (the points tracked in its three frames, [n, 2] each, and the frames'
    camera-to-world poses) with the given poses and with poses fitted to the images; None where fewer than
    MIN_POINTS points have parallax (after the rotation is taken out: a turn in place tells nothing about
    positions) in front of the cameras, or a fit fails."""
    x0, x1, x2 = (np.asarray(x, np.float64) for x in (x0, x1, x2))
    K = np.asarray(K, np.float64)
    fitted = _fitted_views(x0, x1, K)
    if fitted is None:
        return None
    fitted_b, keep = fitted
    x0, x1, x2 = x0[keep], x1[keep], x2[keep]
    w2c = [np.linalg.inv(np.asarray(p, np.float64)) for p in poses_c2w]
    given = _third_view_errors(x0, x1, x2, K, w2c[0], w2c[1], w2c[2])
    ours = _third_view_errors(x0, x1, x2, K, np.eye(4), fitted_b, None)
    if given is None or ours is None:
        return None
    return TripleError(float(np.median(given[0])), float(np.median(ours[0])), int(len(x0)),
                       float(np.median(given[1])))


def _fitted_views(x0: np.ndarray, x1: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The second view's pose (world to camera, the first view at the origin, unit baseline) fitted to the tracks
    by the essential matrix, and the tracks to judge by: its inliers with parallax once its rotation is taken out
    (None with fewer than MIN_POINTS)."""
    if len(x0) < MIN_POINTS:
        return None
    E, mask = cv2.findEssentialMat(x0, x1, K, cv2.RANSAC, 0.999, 1.0)
    if E is None or E.shape != (3, 3):
        return None
    _, R, t, mask = cv2.recoverPose(E, x0, x1, K, mask=mask)
    rotated = (K @ R @ np.linalg.inv(K) @ np.c_[x0, np.ones(len(x0))].T).T
    parallax = np.linalg.norm(rotated[:, :2] / rotated[:, 2:] - x1, axis=1)
    keep = (mask.ravel() > 0) & (parallax > MIN_FLOW_PX)
    if keep.sum() < MIN_POINTS:
        return None
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = R, t.ravel()
    return pose, keep


def _third_view_errors(x0: np.ndarray, x1: np.ndarray, x2: np.ndarray, K: np.ndarray, w2c_a: np.ndarray,
                       w2c_b: np.ndarray, w2c_c: np.ndarray | None) -> tuple[np.ndarray, np.ndarray] | None:
    """(errors in the third view, depths in the first) of the points triangulated from the first two
    (world-to-camera poses): projected with `w2c_c`, or with the pose fitted to them (PnP) where it is None. None
    when fewer than MIN_POINTS points lie in front of the cameras."""
    points = cv2.triangulatePoints(K @ w2c_a[:3], K @ w2c_b[:3], x0.T, x1.T)
    points = (points[:3] / np.where(np.abs(points[3]) > 1e-12, points[3], 1e-12)).T
    depth = (points @ w2c_a[:3, :3].T + w2c_a[:3, 3])[:, 2]
    in_front = depth > 0
    if w2c_c is not None:
        in_front &= (points @ w2c_c[:3, :3].T + w2c_c[:3, 3])[:, 2] > 0
    if in_front.sum() < MIN_POINTS:
        return None
    points, observed = points[in_front], x2[in_front]
    if w2c_c is None:
        w2c_c = _pnp(points, observed, K)
        if w2c_c is None:
            return None
    rvec, _ = cv2.Rodrigues(w2c_c[:3, :3])
    projected, _ = cv2.projectPoints(points, rvec, w2c_c[:3, 3].reshape(3, 1), K, None)
    errors = np.linalg.norm(projected[:, 0] - observed, axis=1)
    return (errors, depth[in_front]) if np.all(np.isfinite(errors)) else None


def _pnp(points: np.ndarray, observed: np.ndarray, K: np.ndarray) -> np.ndarray | None:
    """The world-to-camera pose that fits `points` to `observed` best (RANSAC, then Levenberg-Marquardt on its
    inliers)."""
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(points, observed, K, None, iterationsCount=200,
                                                 reprojectionError=2.0, confidence=0.999, flags=cv2.SOLVEPNP_EPNP)
    if not ok or inliers is None or len(inliers) < 6:
        return None
    inliers = inliers.ravel()
    rvec, tvec = cv2.solvePnPRefineLM(points[inliers], observed[inliers], K, None, rvec, tvec)
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
    return pose


def verdict(errors: list[TripleError], max_ratio: float) -> AgreementVerdict | None:
    """The medians over `errors` (None without any)."""
    if not errors:
        return None
    return AgreementVerdict(float(np.median([e.given_px for e in errors])),
                            float(np.median([e.fitted_px for e in errors])), len(errors), max_ratio)


def sequence_errors(images: list[np.ndarray], poses_c2w: list[np.ndarray], K: np.ndarray, step: int,
                    triples: int) -> list[TripleError]:
    """The errors of up to `triples` triples (i, i + step, i + 2 step) spread along a sequence."""
    last = len(images) - 2 * step
    errors = []
    for i in np.linspace(0, max(0, last - 1), min(triples, max(1, last))).astype(int):
        tracker = TripleTracker(step)
        for j in range(i, min(i + 2 * step + 1, len(images))):
            errors += tracker.add(grey(images[j]), poses_c2w[j], K)
    return errors


class PoseAgreement:
    """Judges a stream's poses from its first frames: a triple starts every `step` frames (its first frame is the
    middle of the one before); a verdict once `triples` triples are measured, or at frame `within_frames` from what
    was."""

    def __init__(self, step: int = 2, triples: int = 8, within_frames: int = 30, max_ratio: float = 1.5) -> None:
        self.triples, self.within_frames, self.max_ratio = triples, within_frames, max_ratio
        self.tracker = TripleTracker(step, every=step)
        self.errors: list[TripleError] = []
        self.frames = 0

    def add(self, image: np.ndarray, pose_c2w: np.ndarray, K: np.ndarray) -> bool:
        """Take the next frame (RGB or grey, its pose, the camera); True once judged (`result`)."""
        self.frames += 1
        self.errors += self.tracker.add(grey(image), pose_c2w, K)
        if len(self.errors) < self.triples and self.frames < self.within_frames:
            return False
        self.tracker.reset()
        return True

    @property
    def scene_depth(self) -> float | None:
        """The median depth of the points the triples triangulated with the given poses (pose units), if any."""
        depths = [e.depth for e in self.errors if np.isfinite(e.depth) and e.depth > 0]
        return float(np.median(depths)) if depths else None

    @property
    def result(self) -> AgreementVerdict | None:
        """The medians over the triples measured so far (None before any had parallax)."""
        return verdict(self.errors, self.max_ratio)

    def forget_frames(self) -> None:
        """A gap in the stream (a frame without a pose): triples start again after it."""
        self.tracker.reset()

    def state_dict(self) -> dict:
        """The measured triples and the frame count (not the images: judging goes on with the next frames)."""
        return {"errors": [[e.given_px, e.fitted_px, e.points, e.depth] for e in self.errors], "frames": self.frames}

    def load_state_dict(self, state: dict) -> None:
        self.errors = [TripleError(float(e[0]), float(e[1]), int(e[2]), float(e[3]) if len(e) > 3 else float("nan"))
                       for e in state["errors"]]
        self.frames = int(state["frames"])
        self.tracker.reset()
