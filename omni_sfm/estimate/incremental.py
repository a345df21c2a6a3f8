"""Every frame that sees lines already fixed in 3D: incremental registration, as the online
tracker poses each new frame (docs/method.md §14, docs/track.md).

A frame that sees lines its predecessors have already fixed in 3D is posed from them, as
incremental structure from motion does with points (:class:`Growth`):

1. **Resection.** The new frame's pose is the absolute pose from the known 3D lines it sees
   (:func:`omni_sfm.estimate.bundle.resect_pose`: the bundle adjustment's residual over the 6
   pose parameters, lines held), started from two predictions: constant velocity and turn rate
   from the last registered frames, and the rotation that best aligns the observed normals with
   the known line directions (``n . R^T d = 0``) with the centre then solved linearly given it
   (``R n . c = R n . p``: each plane passes through its line); the lower robust cost
   wins. A camera that stands still or turns in place is posed like any other: the known
   lines fix its position.
2. **Acceptance.** The frame is kept if at least ``min_lines`` of its known lines fit within
   ``inlier_sigmas`` times the noise, in at least two directions ``min_angle_deg`` apart (one
   direction leaves the position along it free); the pose is then solved again on those.
3. **Triangulation.** Lines the new frame sees that are not yet known are triangulated from all
   registered frames that see them, once their planes have turned by ``min_parallax_deg`` (a
   camera that only turns adds no parallax: its new lines wait) and their residuals fit.
4. **Local adjustment.** Every ``local_every`` frames (and after a frame that fits its lines
   worse than the noise), a bundle adjustment of the last ``local_frames`` registered frames
   and the known lines they see, with every other registered frame that sees those lines held
   (their observations keep the lines in place), stops errors from growing.

**Families** (``families``, on by default). The parallel families that the starting lines show
are fixed world directions (:mod:`omni_sfm.estimate.families`): a known line of a family is
given its direction and keeps it in the local adjustments; a line not yet triangulated whose
planes all contain one family's direction counts in the resection with that direction only
(its normal is orthogonal to it: a constraint on the rotation) and is triangulated with the
direction given. A frame still needs 3 reconstructed lines in two directions (its position).

A frame that fails is reported with the reason; after ``max_misses`` failures in a row the
caller starts again. Cost per frame is bounded by the window: observations are reached through
per-frame and per-track indices, and the local problems are built on the window's observations
only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.estimate.bundle import (
    BundleOptions,
    bundle_adjust,
    observation_residuals,
    resect_pose,
    triangulate_lines,
)
from omni_sfm.estimate.families import (
    camera_anchors,
    family_of_lines,
    family_of_planes,
    line_families,
    point_given_direction,
    snap_to_families,
)
from omni_sfm.geometry import FloatArray, matrix_to_rotvec, rotation_angle, rotvec_to_matrix
from omni_sfm.lines.tracks import LineTracks


@dataclass(frozen=True, kw_only=True)
class IncrementalOptions:
    """Options of the registration (:class:`Growth`; the online tracker's
    ``OnlineOptions.registration``)."""

    min_lines: int = 4
    """Known 3D lines a frame must see and fit (inliers) to be registered (3 lines in two
    directions fix the 6 pose parameters; one more checks them)."""
    min_angle_deg: float = 20.0
    """Two of those lines' directions must be at least this far apart."""
    inlier_sigmas: float = 8.0
    """An observation fits if its angle is at most this many times the noise (per axis)."""
    min_inlier_deg: float = 0.1
    """Floor of that threshold, degrees (noise-free data)."""
    relative_inlier: float = 3.0
    """... or this many times the median angle of the last registered frame, if larger (lines
    triangulated from far away fit a new viewpoint worse than the noise)."""
    max_turn_deg: float = 20.0
    """A registered frame turns at most this much per frame from the last registered one."""
    max_misses: int = 10
    """Failures in a row after which the growth in that direction stops."""
    min_parallax_deg: float = 1.5
    """A new line is triangulated once its world planes span at least this angle."""
    min_views: int = 3
    """... and it is seen in at least this many registered frames."""
    local_every: int = 5
    """A local bundle adjustment after every this many registered frames."""
    local_frames: int = 15
    """Registered frames adjusted by each local adjustment (the latest ones)."""
    local_iterations: int = 10
    """Levenberg-Marquardt iterations of each local adjustment."""
    families: bool = True
    """Use the parallel families that the starting lines show as fixed world directions
    (:mod:`omni_sfm.estimate.families`): their lines constrain a frame's rotation before they
    are triangulated, are triangulated with their direction given and keep it in the local
    adjustments, so the rotation does not drift."""
    family_angle_deg: float = 2.0
    """A line belongs to a family when its direction is within this angle of it."""
    min_family_lines: int = 4
    """A family needs this many starting lines."""



def obs_index(keys: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``(order, starts)``: observations of key ``k`` are ``order[starts[k]:starts[k + 1]]``."""
    order = np.argsort(keys, kind="stable")
    return order, np.searchsorted(keys[order], np.arange(n + 1))


def rotation_from_directions(normals: FloatArray, directions: FloatArray, R0: FloatArray,
                             iterations: int = 8) -> FloatArray:
    """world_from_cam rotation that makes camera-frame normals ``(K, 3)`` orthogonal to their
    lines' world directions ``(K, 3)`` (``n . R^T d = 0``), by Gauss-Newton from ``R0``."""
    R = np.array(R0, np.float64)
    n0, n1, n2 = np.asarray(normals, np.float64).T
    J = np.empty((len(normals), 3))
    for _ in range(iterations):
        a = directions @ R  # R^T d, (K, 3)
        r = np.sum(normals * a, axis=1)
        # J = n x a, d r / d w for R <- R exp([w]x) (numpy's cross product, term for term:
        # the tracker runs this on every frame, and np.cross costs more than the rest)
        a0, a1, a2 = a.T
        J[:, 0] = n1 * a2 - n2 * a1
        J[:, 1] = n2 * a0 - n0 * a2
        J[:, 2] = n0 * a1 - n1 * a0
        w = -np.linalg.solve(J.T @ J + _TINY_EYE, J.T @ r)
        R = R @ rotvec_to_matrix(w)
        x, y, z = w.tolist()
        if math.sqrt(x * x + y * y + z * z) < 1e-12:
            break
    return R


_TINY_EYE = 1e-9 * np.eye(3)


def centre_given_rotation(normals: FloatArray, directions: FloatArray, points: FloatArray,
                          R: FloatArray) -> FloatArray | None:
    """The camera centre that puts every plane (world normal ``m = R n``) through its line's
    point ``p``, least squares: ``m . c = m . p``; None when the lines leave it undetermined
    (all of one direction: the centre is free along it)."""
    del directions  # the rotation has already made each plane contain its line's direction
    m = normals @ R.T
    b = np.sum(m * points, axis=1)
    sv = np.linalg.svd(m, compute_uv=False)
    if len(sv) < 3 or sv[2] < 1e-6 * max(sv[0], 1e-300):
        return None
    return np.asarray(np.linalg.lstsq(m, b, rcond=None)[0])


def plane_parallax_deg(world_normals: FloatArray, line: np.ndarray, num_lines: int
                       ) -> FloatArray:
    """``(num_lines,)`` how far (deg) each line's planes turn about it across its views: the
    world normals ``(N, 3)`` of its observations (``line`` ``(N,)``: which line each is of),
    from the spread of their scatter matrix (0 for a line seen from one place, or only along
    its own direction)."""
    A = np.zeros((num_lines, 3, 3))
    np.add.at(A, line, world_normals[:, :, None] * world_normals[:, None, :])
    ev = np.linalg.eigvalsh(A)
    ratio = ev[:, 1] / np.maximum(ev[:, 1] + ev[:, 2], 1e-300)
    return np.asarray(np.degrees(2.0 * np.arcsin(np.sqrt(np.clip(ratio, 0.0, 1.0)))))


def _spread(directions: FloatArray) -> float:
    """Largest angle (deg) between two of the (unsigned) directions ``(K, 3)``."""
    if len(directions) < 2:
        return 0.0
    g = np.abs(directions @ directions.T)
    return float(np.degrees(np.arccos(np.clip(g.min(), 0.0, 1.0))))


class Growth:
    """The growing reconstruction: poses, known lines and the indices into the observations."""

    def __init__(self, tracks: LineTracks, R: FloatArray, c: FloatArray, est: np.ndarray,
                 d: FloatArray, p: FloatArray, sigma: float, options: IncrementalOptions,
                 bundle: BundleOptions,
                 families: tuple[FloatArray, np.ndarray] | None = None) -> None:
        """``families``: the parallel families' world directions ``(K, 3)`` and each line's
        family ``(M,)`` (-1: none; the known lines of a family already have its direction), as
        an earlier growth found them (:mod:`omni_sfm.estimate.online` carries them from one
        window to the next); None: found here from the known lines (``options.families``)."""
        self.tracks, self.o = tracks, options
        F, M = tracks.num_frames, tracks.num_tracks
        self.R, self.c = np.array(R, np.float64), np.array(c, np.float64)
        self.est = np.array(est, bool)
        self.d, self.p = np.array(d, np.float64), np.array(p, np.float64)
        self.known: np.ndarray = np.asarray(np.isfinite(self.d).all(1) &
                                            np.isfinite(self.p).all(1))
        self.anchored = np.zeros(F, bool)
        """Frames whose rotations the adjustments hold (referred to fixed world directions by
        the caller: :mod:`omni_sfm.estimate.online`)."""
        self.sigma = sigma
        self.thr = max(options.inlier_sigmas * sigma, np.radians(options.min_inlier_deg))
        self.last_median = 0.0  # median angle of the last registered frame at its pose
        self.refit = False  # the last frame fitted its lines worse than usual: adjust soon
        self.by_frame, self.frame_starts = obs_index(tracks.obs_frame, F)
        self.by_track, self.track_starts = obs_index(tracks.obs_track, M)
        self.D = np.zeros((0, 3))
        self.fam = np.full(M, -1)
        if families is not None:
            self.D, self.fam = np.array(families[0], np.float64).reshape(-1, 3), \
                np.array(families[1], np.int64)
        elif options.families and self.known.any():
            self.D, self.fam = line_families(np.where(self.known[:, None], self.d, np.nan),
                                             max_angle_deg=options.family_angle_deg,
                                             min_lines=options.min_family_lines)
            self.snap(np.flatnonzero(self.fam >= 0))
        self.local = replace(bundle, max_rounds=2, max_iterations=options.local_iterations,
                             final_loss=None)

    def snap(self, lines: np.ndarray) -> None:
        """Give the known ``lines`` of a family exactly its direction, turning each about its
        point nearest the registered cameras that see it."""
        lines = np.unique(lines)
        if len(lines) == 0:
            return
        obs = self.track_obs(lines)
        obs = obs[self.est[self.tracks.obs_frame[obs]]]
        local = np.searchsorted(lines, self.tracks.obs_track[obs])
        anchors = camera_anchors(self.tracks.obs_frame[obs], local, self.c, len(lines))
        self.d[lines], self.p[lines] = snap_to_families(self.d[lines], self.p[lines], self.D,
                                                        self.fam[lines], anchors)

    def frame_obs(self, f: int) -> np.ndarray:
        return self.by_frame[self.frame_starts[f]:self.frame_starts[f + 1]]

    def track_obs(self, tracks: np.ndarray) -> np.ndarray:
        if len(tracks) == 0:
            return np.zeros(0, int)
        return np.concatenate([self.by_track[self.track_starts[t]:self.track_starts[t + 1]]
                               for t in tracks])

    # -- 1-2: resection and acceptance ---------------------------------------------------------
    def predict(self, f: int, a: int, b: int | None) -> tuple[FloatArray, FloatArray]:
        """Pose at ``f`` from registered ``a`` (nearest) and ``b`` (the one before it)."""
        if b is None:
            return self.R[a], self.c[a]
        k = (f - a) / (a - b)
        step = matrix_to_rotvec(self.R[b].T @ self.R[a])
        return self.R[a] @ rotvec_to_matrix(step * k), self.c[a] + (self.c[a] - self.c[b]) * k

    def register(self, f: int, a: int, b: int | None) -> str | None:
        """Pose frame ``f``; None on success, else why not."""
        tracks, o = self.tracks, self.o
        obs = self.frame_obs(f)
        t = tracks.obs_track[obs]
        kn = self.known[t]
        fo = ~kn & (self.fam[t] >= 0)  # lines of a family, not triangulated yet
        if kn.sum() < 3 or kn.sum() + fo.sum() < o.min_lines:
            return (f"sees {int(kn.sum())} lines already reconstructed and "
                    f"{int(fo.sum())} others of a known direction; need 3 and {o.min_lines} "
                    f"in all (of {len(t)} lines seen)")
        n, d, p = tracks.obs_normal[obs[kn]], self.d[t[kn]], self.p[t[kn]]
        m, D = tracks.obs_normal[obs[fo]], self.D[self.fam[t[fo]]]
        K = len(n)
        R_pred, c_pred = self.predict(f, a, b)
        starts = [(R_pred, c_pred)]
        R_dir = rotation_from_directions(np.concatenate([n, m]), np.concatenate([d, D]), R_pred)
        c_dir = centre_given_rotation(n, d, p, R_dir)
        if c_dir is not None:
            starts.append((R_dir, c_dir))
        # lines fixed from far away fit new viewpoints worse than the noise: the threshold
        # follows how well the last frame fitted them
        thr = max(self.thr, o.relative_inlier * self.last_median)
        best = None
        for R0, c0 in starts:
            R1, c1, ang = resect_pose(n, d, p, R0, c0, scale=thr / 2.0,
                                      direction_normals=m, directions=D)
            inl = ang <= thr
            score = (int(inl.sum()), -float(np.sum(np.minimum(ang, thr) ** 2)))
            if best is None or score > best[0]:
                best = (score, R1, c1, inl)
        assert best is not None
        _, R1, c1, inl = best
        il, idir = inl[:K], inl[K:]
        if il.sum() < 3 or inl.sum() < o.min_lines:
            return (f"{int(il.sum())} of its {K} reconstructed lines and {int(idir.sum())} of "
                    f"{len(m)} of a known direction fit a pose; need 3 and {o.min_lines} in all")
        if _spread(d[il]) < o.min_angle_deg:
            # lines of other known directions fix the rotation, not the position along these
            return "the reconstructed lines it sees are all (nearly) parallel"
        R2, c2, ang = resect_pose(n[il], d[il], p[il], R1, c1, scale=np.inf,
                                  direction_normals=m[idir], directions=D[idir])
        turn = float(np.degrees(rotation_angle(self.R[a].T @ R2)))
        if turn > o.max_turn_deg * abs(f - a):
            return f"its pose would turn {turn:.0f} deg from frame {a}"
        self.R[f], self.c[f], self.est[f] = R2, c2, True
        self.last_median = float(np.median(ang[:int(il.sum())]))
        self.refit = self.last_median > self.thr / 2.0
        return None

    # -- 3: triangulation ----------------------------------------------------------------------
    def triangulate(self, f: int) -> None:
        """Lines seen in ``f`` that are not known yet, from all registered frames seeing them."""
        tracks, o = self.tracks, self.o
        t = tracks.obs_track[self.frame_obs(f)]
        cand = np.unique(t[~self.known[t]])
        if len(cand) == 0:
            return
        obs = self.track_obs(cand)
        obs = obs[self.est[tracks.obs_frame[obs]]]
        if len(obs) == 0:
            return
        local_t = np.searchsorted(cand, tracks.obs_track[obs])
        cnt = np.bincount(local_t, minlength=len(cand))
        n_w = np.einsum("kij,kj->ki", self.R[tracks.obs_frame[obs]], tracks.obs_normal[obs])
        if len(self.D):
            self.fam[cand] = family_of_planes(n_w, local_t, len(cand), self.D,
                                              max_angle_deg=np.degrees(self.thr),
                                              min_views=o.min_views)
            of = self.fam[cand] >= 0
            self.triangulate_in_family(cand[of], obs[of[local_t]], n_w[of[local_t]])
            keep = ~of[local_t]
            cand, obs, n_w = cand[~of], obs[keep], n_w[keep]
            if len(cand) == 0:
                return
            local_t = np.searchsorted(cand, tracks.obs_track[obs])
            cnt = np.bincount(local_t, minlength=len(cand))
        parallax = plane_parallax_deg(n_w, local_t, len(cand))
        ready = (cnt >= o.min_views) & (parallax >= o.min_parallax_deg)
        if not ready.any():
            return
        keep = ready[local_t]
        sub = tracks.subset(obs[keep], cand)
        dd, pp, ok = triangulate_lines(sub, self.R, self.c, min_observations=o.min_views)
        ang = observation_residuals(sub, self.R, self.c, dd, pp)
        rms = np.sqrt(np.bincount(sub.obs_track, ang ** 2, len(cand)) /
                      np.maximum(np.bincount(sub.obs_track, minlength=len(cand)), 1))
        good = ok & (rms <= self.thr)
        self.d[cand[good]], self.p[cand[good]] = dd[good], pp[good]
        self.known[cand[good]] = True
        if len(self.D):  # a new line of a family takes its direction
            new = cand[good]
            self.fam[new] = family_of_lines(self.d[new], self.D,
                                            max_angle_deg=self.o.family_angle_deg)
            self.snap(new[self.fam[new] >= 0])

    def triangulate_in_family(self, lines: np.ndarray, obs: np.ndarray, n_w: FloatArray) -> None:
        """Lines of a family (their direction known), from their registered views ``obs`` with
        world normals ``n_w``: once their planes turn by ``min_parallax_deg`` about the direction
        (only the line's position is unknown) in ``min_views`` views that fit."""
        tracks, o = self.tracks, self.o
        for t in lines:
            mine = tracks.obs_track[obs] == t
            if mine.sum() < o.min_views:
                continue
            D = self.D[self.fam[t]]
            c = self.c[tracks.obs_frame[obs[mine]]]
            p, spread = point_given_direction(n_w[mine], c, D)
            if np.degrees(spread) < o.min_parallax_deg:
                continue
            sub = tracks.subset(obs[mine], np.array([t]))
            ang = observation_residuals(sub, self.R, self.c, D[None], p[None])
            if float(np.sqrt(np.mean(ang ** 2))) <= self.thr:
                self.d[t], self.p[t], self.known[t] = D, p, True

    # -- 4: local adjustment -------------------------------------------------------------------
    def adjust(self, window: np.ndarray, options: BundleOptions | None = None) -> None:
        """Bundle adjustment of the registered frames ``window`` and the known lines they see;
        every other registered frame that sees those lines takes part, held (its observations
        keep the lines where the earlier frames put them: in a stop, the window alone would
        leave the lines' depths free)."""
        tracks = self.tracks
        obs = np.concatenate([self.frame_obs(int(k)) for k in window])
        lines = np.unique(tracks.obs_track[obs])
        lines = lines[self.known[lines]]
        if len(lines) < 3:
            return
        obs = self.track_obs(lines)
        obs = obs[self.est[tracks.obs_frame[obs]]]
        frames = np.unique(tracks.obs_frame[obs])
        held = np.setdiff1d(frames, window)
        if len(held) == 0:
            return
        lines = np.sort(lines)
        sub = tracks.subset(obs, lines, frames)
        held_sub = np.isin(frames, held)
        c_held = self.c[held]
        spread = len(held) > 1 and float(np.ptp(c_held, axis=0).max()) > 0
        try:
            res = bundle_adjust(sub, self.R[frames], self.c[frames], self.d[lines],
                                self.p[lines], held_frames=held_sub,
                                held_directions=self.fam[lines] >= 0,
                                held_rotations=self.anchored[frames],
                                scale_frames=held_sub if spread else None,
                                options=options or self.local)
        except OmniSfmError:
            return
        ok = res.frames
        self.R[frames[ok]], self.c[frames[ok]] = res.rotations[ok], res.positions[ok]
        used = res.used_tracks
        self.d[lines[used]], self.p[lines[used]] = res.line_directions[used], \
            res.line_points[used]
        bad = lines[res.outlier_tracks]
        self.known[bad] = False
        self.d[bad], self.p[bad] = np.nan, np.nan
        self.fam[bad] = -1
