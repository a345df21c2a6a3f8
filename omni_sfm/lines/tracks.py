"""Line tracks: the observations every later stage consumes, and the ``tracks.json`` format.

``tracks.json`` (documented in docs/formats.md)::

    {"num_frames": 200,
     "timestamps": [0, 1, ...],          # optional, one per frame (default: frame index)
     "tracks": [{"id": 0, "frames": [0, 1, 2, 5], "normals": [[nx, ny, nz], ...],
                 "rays": [[rx, ry, rz], ...]},     # optional, see below
                ...]}

``normals[j]`` is the unit normal of the plane through the viewpoint and the 3D line, in the
camera frame of frame ``frames[j]``; its sign is arbitrary. Extra keys are ignored.

``rays[j]`` (optional, all tracks or none) is a unit ray from the viewpoint towards a point of
the observed segment (e.g. its middle), in the same camera frame. Normals alone determine the
camera centres only up to a point reflection through the first camera (a plane's normal has no
side); the rays tell on which side each line is seen, which fixes that sign.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.fileio import atomic_write_text, dumps_json, read_json
from omni_sfm.geometry import FloatArray

IntArray = np.ndarray


@dataclass(frozen=True)
class LineTracks:
    """Observed line normals ("NVs"), flat over all tracks.

    Attributes:
        num_frames: number of frames ``F`` of the sequence.
        track_ids: ``(M,)`` int, the id of each track (as in the file).
        obs_track: ``(K,)`` int, index into ``track_ids`` of each observation.
        obs_frame: ``(K,)`` int in ``[0, F)``, frame of each observation.
        obs_normal: ``(K, 3)`` unit normals in that frame's camera frame (sign arbitrary).
        timestamps: ``(F,)`` time of each frame (frame index or seconds).
        obs_ray: ``(K, 3)`` unit ray towards a point of each observed segment (camera frame),
            or None when only normals are known (then the solution has a reflection ambiguity).
        obs_sigma: ``(K, 2)`` standard deviations (radians) of each normal's error along the
            two directions perpendicular to it: ``[0]`` along the ray (projected into the
            line's plane), ``[1]`` along ``normal x ray``; or None (all observations alike).
            Needs ``obs_ray``. A short segment fixes its plane's tilt about its own ray
            poorly, so ``[1]`` is the larger; the bundle adjustment weights by them.
        obs_offset: ``(K, 3)`` the centre of the lens that took each observation, in that
            frame's camera frame (a rig of lenses, :class:`~omni_sfm.cameras.RigCamera`: the
            frame's pose is the rig's), in metres as the front end and ``tracks.json`` give
            them; or None (a central camera: every observation from the frame's centre). The
            global estimator adjusts a rig in metres (docs/estimator.md, "Rigs").

    Observations are sorted by (track, frame); a track sees a frame at most once.
    """

    num_frames: int
    track_ids: IntArray
    obs_track: IntArray
    obs_frame: IntArray
    obs_normal: FloatArray
    timestamps: FloatArray
    obs_ray: FloatArray | None = None
    obs_sigma: FloatArray | None = None
    obs_offset: FloatArray | None = None

    @property
    def num_tracks(self) -> int:
        return int(self.track_ids.shape[0])

    @property
    def num_observations(self) -> int:
        return int(self.obs_track.shape[0])

    def visibility(self) -> np.ndarray:
        """``(M, F)`` bool: track m is observed in frame f."""
        vis = np.zeros((self.num_tracks, self.num_frames), dtype=bool)
        vis[self.obs_track, self.obs_frame] = True
        return vis

    def frame_spans(self, obs: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(M,)`` the first and ``(M,)`` the last frame in which each track is observed
        (among the observations ``obs`` ``(K,)`` bool, all when None); ``num_frames`` and -1
        for a track without one."""
        t, f = (self.obs_track, self.obs_frame) if obs is None else \
            (self.obs_track[obs], self.obs_frame[obs])
        first = np.full(self.num_tracks, self.num_frames)
        last = np.full(self.num_tracks, -1)
        np.minimum.at(first, t, f)
        np.maximum.at(last, t, f)
        return first, last

    def dense_normals(self) -> FloatArray:
        """``(M, F, 3)`` normals, NaN where a track is not observed."""
        out = np.full((self.num_tracks, self.num_frames, 3), np.nan)
        out[self.obs_track, self.obs_frame] = self.obs_normal
        return out

    def select_tracks(self, keep: np.ndarray) -> LineTracks:
        """The tracks at indices ``keep`` (int array or (M,) bool mask), re-indexed."""
        idx = np.flatnonzero(keep) if np.asarray(keep).dtype == bool else np.asarray(keep)
        remap = np.full(self.num_tracks, -1)
        remap[idx] = np.arange(len(idx))
        sel = remap[self.obs_track] >= 0
        return LineTracks(self.num_frames, self.track_ids[idx], remap[self.obs_track[sel]],
                          self.obs_frame[sel], self.obs_normal[sel], self.timestamps,
                          None if self.obs_ray is None else self.obs_ray[sel],
                          None if self.obs_sigma is None else self.obs_sigma[sel],
                          None if self.obs_offset is None else self.obs_offset[sel])

    def keep_observations(self, keep: np.ndarray) -> LineTracks:
        """These tracks with only the observations ``keep`` (``(K,)`` bool, or indices in
        order); tracks and frames keep their numbers."""
        obs = np.flatnonzero(keep) if np.asarray(keep).dtype == bool else np.asarray(keep)
        return self.subset(obs, np.arange(self.num_tracks))

    def subset(self, obs: np.ndarray, lines: np.ndarray,
               frames: np.ndarray | None = None) -> LineTracks:
        """The observations ``obs`` (indices, in order) as tracks ``0..len(lines)-1`` (``lines``
        sorted, holding every track of ``obs``); their frames renumbered ``0..len(frames)-1`` if
        ``frames`` (sorted, holding every frame of ``obs``) is given, else kept."""
        f = self.obs_frame[obs]
        num, ts = self.num_frames, self.timestamps
        if frames is not None:
            f = np.searchsorted(frames, f)
            num, ts = len(frames), self.timestamps[frames]
        return LineTracks(
            num_frames=num, track_ids=self.track_ids[lines],
            obs_track=np.searchsorted(lines, self.obs_track[obs]), obs_frame=f,
            obs_normal=self.obs_normal[obs], timestamps=ts,
            obs_ray=None if self.obs_ray is None else self.obs_ray[obs],
            obs_sigma=None if self.obs_sigma is None else self.obs_sigma[obs],
            obs_offset=None if self.obs_offset is None else self.obs_offset[obs])

    def with_offset_scale(self, scale: float) -> LineTracks:
        """These tracks with the lens offsets times ``scale`` (the estimator's length units
        per metre); unchanged without offsets."""
        if self.obs_offset is None:
            return self
        return replace(self, obs_offset=self.obs_offset * float(scale))

    def _as_stored(self) -> tuple[FloatArray, FloatArray | None, FloatArray | None,
                                  FloatArray | None]:
        """The numbers ``tracks.json`` stores: normals and rays rounded to 15 decimals, the
        sigmas in degrees to 9, the lens offsets (metres) to 12 (JSON then holds each of these
        doubles exactly)."""
        rays = None if self.obs_ray is None else np.round(self.obs_ray, 15)
        sig: FloatArray | None = None if self.obs_sigma is None else \
            np.asarray(np.round(np.degrees(self.obs_sigma), 9), dtype=np.float64)
        off = None if self.obs_offset is None else np.round(self.obs_offset, 12)
        return np.round(self.obs_normal, 15), rays, sig, off

    def as_written(self) -> LineTracks:
        """These tracks exactly as :func:`read_tracks` gives them back from the
        ``tracks.json`` that :func:`write_tracks` writes of them (the numbers rounded as the
        file stores them, then normalised as reading does). The estimator's choices follow the
        last bits of its input (docs/estimator.md, "Speed"): ``init`` on images estimates from
        these, so that ``init --tracks tracks.json`` gives its poses to the bit. (Written again,
        these numbers give the same file: each rounding is idempotent on its own result.)"""
        normals, rays, sigmas_deg, offsets = self._as_stored()
        return make_tracks(self.num_frames, self.track_ids, self.obs_track, self.obs_frame,
                           normals, self.timestamps, obs_ray=rays,
                           obs_sigma=None if sigmas_deg is None else np.radians(sigmas_deg),
                           obs_offset=offsets, as_stored=True)

    def to_json_dict(self) -> dict[str, Any]:
        normals, rays, sigmas_deg, offsets = self._as_stored()
        tracks = []
        # each track's observations in their order (one sort, not a mask per track, which would
        # be tracks x observations comparisons, seconds on a long video's tracks)
        order = np.argsort(self.obs_track, kind="stable")
        bounds = np.searchsorted(self.obs_track[order], np.arange(self.num_tracks + 1))
        for m in range(self.num_tracks):
            sel = order[bounds[m]:bounds[m + 1]]
            entry = {"id": int(self.track_ids[m]),
                     "frames": self.obs_frame[sel].tolist(),
                     "normals": normals[sel].tolist()}
            if rays is not None:
                entry["rays"] = rays[sel].tolist()
            if sigmas_deg is not None:
                entry["sigmas_deg"] = sigmas_deg[sel].tolist()
            if offsets is not None:
                entry["offsets_m"] = offsets[sel].tolist()
            tracks.append(entry)
        return {"num_frames": self.num_frames, "timestamps": self.timestamps.tolist(),
                "tracks": tracks}


def _checked_normals(num_frames: int, track_ids: IntArray, t: IntArray, f: IntArray,
                     n: FloatArray, source: str) -> FloatArray:
    """Check the normals (finite, unit) and frame indices (in range); the normals' lengths."""
    if not np.isfinite(n).all():
        raise OmniSfmError(f"{source}: normals must be finite (found NaN or inf)")
    norms = np.linalg.norm(n, axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > 1e-3)
    if bad.size:
        raise OmniSfmError(f"{source}: normals must be unit vectors; observation of track "
                           f"{int(track_ids[t[bad[0]]])} has length {norms[bad[0]]:.6g}")
    out = np.flatnonzero((f < 0) | (f >= num_frames))
    if out.size:
        raise OmniSfmError(f"{source}: frame index {int(f[out[0]])} of track "
                           f"{int(track_ids[t[out[0]]])} is outside [0, {num_frames})")
    return norms


def _checked_rays(obs_ray: FloatArray | None, n: FloatArray, norms: FloatArray,
                  source: str) -> FloatArray | None:
    """The observations' rays as ``(N, 3)``, checked to be unit and in their line's plane."""
    if obs_ray is None:
        return None
    rays = np.asarray(obs_ray, dtype=np.float64).reshape(-1, 3)
    if rays.shape != n.shape:
        raise OmniSfmError(f"{source}: need one ray per normal, got {rays.shape[0]} rays "
                           f"for {n.shape[0]} normals")
    rn = np.linalg.norm(rays, axis=1)
    if not np.isfinite(rays).all() or np.any(np.abs(rn - 1.0) > 1e-3):
        raise OmniSfmError(f"{source}: rays must be finite unit vectors")
    if np.any(np.abs(np.sum(rays * n, axis=1)) / norms > 0.05):
        raise OmniSfmError(f"{source}: a ray does not lie in its line's plane "
                           "(|ray . normal| > 0.05)")
    return rays


def _checked_sigmas(obs_sigma: FloatArray | None, rays: FloatArray | None, n: FloatArray,
                    source: str) -> FloatArray | None:
    """The observations' ``[sigma_along, sigma_across]`` as ``(N, 2)``, checked positive."""
    if obs_sigma is None:
        return None
    if rays is None:
        raise OmniSfmError(f"{source}: sigmas need rays (they are given along the ray)")
    sig = np.asarray(obs_sigma, dtype=np.float64).reshape(-1, 2)
    if sig.shape[0] != n.shape[0]:
        raise OmniSfmError(f"{source}: need one [sigma_along, sigma_across] per normal, got "
                           f"{sig.shape[0]} for {n.shape[0]} normals")
    if not np.isfinite(sig).all() or np.any(sig <= 0):
        raise OmniSfmError(f"{source}: sigmas must be finite and positive")
    return sig


def _checked_offsets(obs_offset: FloatArray | None, n: FloatArray,
                     source: str) -> FloatArray | None:
    """The observations' lens offsets (metres) as ``(N, 3)``, checked finite."""
    if obs_offset is None:
        return None
    off = np.asarray(obs_offset, dtype=np.float64).reshape(-1, 3)
    if off.shape != n.shape:
        raise OmniSfmError(f"{source}: need one lens offset per normal, got {off.shape[0]} "
                           f"for {n.shape[0]} normals")
    if not np.isfinite(off).all():
        raise OmniSfmError(f"{source}: lens offsets must be finite")
    return off


def _unit(v: FloatArray, length: FloatArray, as_stored: bool) -> FloatArray:
    """``v / length`` row-wise; with ``as_stored``, lengths within 1e-12 of 1 count as 1."""
    if as_stored:
        length = np.where(np.abs(length - 1.0) <= 1e-12, 1.0, length)
    return np.asarray(v / length[:, None])


def _checked_timestamps(num_frames: int, timestamps: FloatArray | None,
                        source: str) -> FloatArray:
    """The frames' timestamps (the frame indices when none are given), checked finite."""
    ts = np.arange(num_frames, dtype=np.float64) if timestamps is None else \
        np.asarray(timestamps, dtype=np.float64)
    if ts.shape != (num_frames,) or not np.isfinite(ts).all():
        raise OmniSfmError(f"{source}: 'timestamps' must be {num_frames} finite numbers")
    return ts


def make_tracks(num_frames: int, track_ids: IntArray, obs_track: IntArray, obs_frame: IntArray,
                obs_normal: FloatArray, timestamps: FloatArray | None = None,
                source: str = "tracks", obs_ray: FloatArray | None = None,
                obs_sigma: FloatArray | None = None, *, obs_offset: FloatArray | None = None,
                as_stored: bool = False) -> LineTracks:
    """Validate and sort observations into a :class:`LineTracks` (errors name ``source``).

    Normals and rays are normalised; with ``as_stored`` (the numbers of a ``tracks.json``),
    those within 1e-12 of unit length are taken as they are, so that the file's numbers and
    the tracks' are the same (normalising rounded unit vectors moves their last bits, and
    rounded again they can land on other decimals: :meth:`LineTracks.as_written`)."""
    if isinstance(num_frames, bool) or not isinstance(num_frames, int | np.integer) \
            or num_frames < 1:
        raise OmniSfmError(f"{source}: 'num_frames' must be a positive integer, got {num_frames!r}")
    n = np.asarray(obs_normal, dtype=np.float64).reshape(-1, 3)
    t = np.asarray(obs_track, dtype=np.int64)
    f = np.asarray(obs_frame, dtype=np.int64)
    norms = _checked_normals(num_frames, track_ids, t, f, n, source)
    rays = _checked_rays(obs_ray, n, norms, source)
    sig = _checked_sigmas(obs_sigma, rays, n, source)
    off = _checked_offsets(obs_offset, n, source)
    order = np.lexsort((f, t))
    t, f, n = t[order], f[order], _unit(n[order], norms[order], as_stored)
    if rays is not None:
        rays = _unit(rays[order], np.linalg.norm(rays[order], axis=1), as_stored)
    if sig is not None:
        sig = sig[order]
    if off is not None:
        off = off[order]
    dup = np.flatnonzero((np.diff(t) == 0) & (np.diff(f) == 0))
    if dup.size:
        raise OmniSfmError(f"{source}: track {int(track_ids[t[dup[0]]])} lists frame "
                           f"{int(f[dup[0]])} twice")
    ts = _checked_timestamps(num_frames, timestamps, source)
    return LineTracks(int(num_frames), np.asarray(track_ids, dtype=np.int64), t, f, n, ts, rays,
                      sig, off)


def _track_numbers(path: Path, k: int, tr: Any) -> tuple[Any, FloatArray, FloatArray]:
    """Track ``#k``'s id, frame indices and normals, checked for shape and type."""
    if not isinstance(tr, dict) or not {"frames", "normals"} <= tr.keys():
        raise OmniSfmError(f"{path}: track #{k} needs keys 'frames' and 'normals'")
    tid = tr.get("id", k)
    try:
        fr = np.asarray(tr["frames"], dtype=np.float64).reshape(-1)
        nv = np.asarray(tr["normals"], dtype=np.float64)
    except (TypeError, ValueError):
        raise OmniSfmError(f"{path}: track {tid}: 'frames' and 'normals' must be numbers") \
            from None
    if nv.ndim != 2 or nv.shape[1] != 3 or nv.shape[0] != fr.shape[0]:
        raise OmniSfmError(f"{path}: track {tid}: needs one [nx, ny, nz] per frame, got "
                           f"{fr.shape[0]} frames and normals of shape {nv.shape}")
    if not np.all(fr == np.round(fr)):
        raise OmniSfmError(f"{path}: track {tid}: frame indices must be integers")
    if not isinstance(tid, int) or isinstance(tid, bool):
        raise OmniSfmError(f"{path}: track #{k}: 'id' must be an integer, got {tid!r}")
    return tid, fr, nv


def _track_vectors(path: Path, tid: int, tr: dict[str, Any], key: str, what: str,
                   nv: FloatArray) -> FloatArray:
    """A track's ``key`` (``rays``, ``offsets_m``): one ``[x, y, z]`` ``what`` per normal."""
    try:
        v = np.asarray(tr[key], dtype=np.float64)
    except (TypeError, ValueError):
        raise OmniSfmError(f"{path}: track {tid}: '{key}' must be numbers") from None
    if v.shape != nv.shape:
        raise OmniSfmError(f"{path}: track {tid}: needs one {what} per normal, got '{key}' "
                           f"of shape {v.shape}")
    return v


def _track_sigmas(path: Path, tid: int, tr: dict[str, Any], nv: FloatArray) -> FloatArray:
    """A track's ``sigmas_deg`` in radians, one ``[along, across]`` pair per normal."""
    try:
        sv = np.radians(np.asarray(tr["sigmas_deg"], dtype=np.float64))
    except (TypeError, ValueError):
        raise OmniSfmError(f"{path}: track {tid}: 'sigmas_deg' must be numbers") \
            from None
    if sv.shape != (nv.shape[0], 2):
        raise OmniSfmError(f"{path}: track {tid}: needs one [along, across] pair of "
                           f"sigmas per normal, got shape {sv.shape}")
    return sv


def read_tracks(path: Path | str) -> LineTracks:
    """Read and validate a ``tracks.json`` file; defects become one-line OmniSfmErrors."""
    path = Path(path)
    data = read_json(path, "tracks file")
    if not isinstance(data, dict) or "tracks" not in data or "num_frames" not in data:
        raise OmniSfmError(f"{path}: tracks file needs keys 'num_frames' and 'tracks'")
    tracks = data["tracks"]
    if not isinstance(tracks, list):
        raise OmniSfmError(f"{path}: 'tracks' must be a list")
    ids, ot, of, on, orays, osig, ooff = [], [], [], [], [], [], []
    for k, tr in enumerate(tracks):
        tid, fr, nv = _track_numbers(path, k, tr)
        if "rays" in tr:
            orays.append(_track_vectors(path, tid, tr, "rays", "ray", nv))
        if "sigmas_deg" in tr:
            osig.append(_track_sigmas(path, tid, tr, nv))
        if "offsets_m" in tr:
            ooff.append(_track_vectors(path, tid, tr, "offsets_m", "lens offset", nv))
        ids.append(tid)
        ot.append(np.full(fr.shape[0], k))
        of.append(fr.astype(np.int64))
        on.append(nv)
    if len(set(ids)) != len(ids):
        raise OmniSfmError(f"{path}: track ids must be unique")
    if not ids:
        raise OmniSfmError(f"{path}: no tracks")
    if orays and len(orays) != len(ids):
        raise OmniSfmError(f"{path}: 'rays' must be given for all tracks or for none")
    if osig and len(osig) != len(ids):
        raise OmniSfmError(f"{path}: 'sigmas_deg' must be given for all tracks or for none")
    if ooff and len(ooff) != len(ids):
        raise OmniSfmError(f"{path}: 'offsets_m' must be given for all tracks or for none")
    return make_tracks(data["num_frames"], np.asarray(ids), np.concatenate(ot),
                       np.concatenate(of), np.concatenate(on, axis=0).reshape(-1, 3),
                       data.get("timestamps"), source=str(path),
                       obs_ray=np.concatenate(orays, axis=0) if orays else None,
                       obs_sigma=np.concatenate(osig, axis=0) if osig else None,
                       obs_offset=np.concatenate(ooff, axis=0) if ooff else None,
                       as_stored=True)


def write_tracks(path: Path | str, tracks: LineTracks) -> None:
    """Write ``tracks`` as ``tracks.json`` (atomically)."""
    atomic_write_text(Path(path), dumps_json(tracks.to_json_dict()))


def reversed_frames(tracks: LineTracks) -> LineTracks:
    """``tracks`` with frame ``k`` as frame ``F - 1 - k`` (the timestamps stay in order: the
    estimator does not use them)."""
    f = tracks.num_frames - 1 - tracks.obs_frame
    order = np.lexsort((f, tracks.obs_track))  # by track, then frame, as every LineTracks

    def rows(a: FloatArray | None) -> FloatArray | None:
        return None if a is None else a[order]

    return replace(tracks, obs_track=tracks.obs_track[order], obs_frame=f[order],
                   obs_normal=tracks.obs_normal[order], obs_ray=rows(tracks.obs_ray),
                   obs_sigma=rows(tracks.obs_sigma), obs_offset=rows(tracks.obs_offset))
