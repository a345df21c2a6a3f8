"""The stages' reports, one frozen dataclass each with its JSON form, read and written here.

- :class:`InitReport`: an init folder's ``report.json``, as the line-based estimator (which
  writes it itself) or :class:`PluginInitReport` (``init --initializer``) wrote it;
- :class:`RefineReport`, :class:`DenseReport`: a refine or dense folder's ``report.json``;
- :class:`ExportReport`: an export's ``report.json``;
- :class:`CompareResults` (of :class:`CompareEntry`): a comparison's ``results.json``;
- :class:`StageReport`: any stage folder's ``report.json``, read for what each may record
  (where its frames and its input folder are, the parallel family);
- :class:`TrackFrame`: a line of ``omni-sfm track``'s ``frames.jsonl`` (read here:
  :func:`read_track_frames`; ``TrackedPose.to_json`` writes it).

The folders' loaders (:mod:`omni_sfm.folders`) read them; nothing else parses these files.

Every field is a top-level key of the JSON document, of the same name, in the order written
(docs/formats.md, docs/colmap.md, docs/dense.md, docs/comparison.md). A field that may be
absent is None when it is (the key is then not written). A section read key by key is a
dataclass of its own (:class:`MapperReport`, :class:`ScaleReport`, ...), (de)serialised by the
same two methods; the keys it does not name are kept in its ``other`` and written back at their
place, so a file read and written again is the same to the byte. Sections nobody reads key by
key stay JSON objects (``dict``). :meth:`JsonReport.to_json` gives the document,
:meth:`JsonReport.from_json` reads one back (a one-line OmniSfmError when a required key is
missing), :meth:`JsonReport.write` and :meth:`JsonReport.read` go through files (atomic write).
Numpy arrays in a report are written as lists; a report read back holds what JSON holds.
"""

from __future__ import annotations

import types
import typing
from collections.abc import Mapping
from dataclasses import MISSING, dataclass, field, fields
from pathlib import Path
from typing import Any, TypeVar

from omni_sfm.errors import OmniSfmError
from omni_sfm.fileio import atomic_write_text, dumps_json, read_json, resolve_stored

_OMIT = "omit_when_none"
_REST = "other_keys"

R = TypeVar("R", bound="JsonReport")


def absent() -> Any:
    """A field whose key is not written when it is None."""
    return field(default=None, metadata={_OMIT: True})


def other_keys() -> Any:
    """The field holding the keys no other field names, written at its place."""
    return field(default_factory=dict, metadata={_REST: True})


def _dump(value: Any) -> Any:
    """``value`` with every report in it (nested in lists and dicts) as its JSON document."""
    if isinstance(value, JsonReport):
        return value.to_json()
    if isinstance(value, list):
        return [_dump(v) for v in value]
    if isinstance(value, dict):
        return {k: _dump(v) for k, v in value.items()}
    return value


_HINTS: dict[type, dict[str, Any]] = {}


def _hints(cls: type) -> dict[str, Any]:
    """The fields' types of the dataclass ``cls`` (its annotations resolved, once)."""
    if cls not in _HINTS:
        _HINTS[cls] = typing.get_type_hints(cls)
    return _HINTS[cls]


def _load(hint: Any, value: Any, where: str) -> Any:
    """``value`` of a JSON document read as the field type ``hint``: a report type (alone, in
    ``X | None``, ``list[X]`` or ``dict[str, X]``) is read with its ``from_json``; anything
    else is kept as JSON holds it."""
    if value is None or hint is Any:
        return value
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        kinds = [a for a in args if a is not type(None)]
        return _load(kinds[0], value, where) if len(kinds) == 1 else value
    if isinstance(hint, type) and issubclass(hint, JsonReport):
        return hint.from_json(value, where)
    if origin is list and isinstance(value, list):
        return [_load(args[0], v, f"{where}[{k}]") for k, v in enumerate(value)]
    if origin is dict and isinstance(value, Mapping) and len(args) == 2:
        return {k: _load(args[1], v, f"{where}.{k}") for k, v in value.items()}
    return value


class JsonReport:
    """JSON form of a frozen dataclass report (a mixin; see the module docstring).

    A field whose type is a report (``X``, ``X | None``, ``list[X]``, ``dict[str, X]``) is
    written as that report's document and read back with that report's :meth:`from_json`, so
    a section typed as its own dataclass needs no (de)serialisation of its own."""

    def to_json(self) -> dict[str, Any]:
        """The JSON document: the fields in order, their keys the fields' names."""
        out: dict[str, Any] = {}
        for f in fields(self):  # type: ignore[arg-type]
            value = getattr(self, f.name)
            if f.metadata.get(_REST):
                out.update(value)
            elif value is not None or not f.metadata.get(_OMIT):
                out[f.name] = _dump(value)
        return out

    @classmethod
    def from_json(cls: type[R], doc: Any, where: str = "report") -> R:
        """The report of the JSON document ``doc``; a one-line OmniSfmError naming ``where``
        when it is not an object or lacks a required key."""
        if not isinstance(doc, Mapping):
            raise OmniSfmError(f"{where}: not a JSON object")
        kwargs: dict[str, Any] = {}
        rest, named = None, set()
        hints = _hints(cls)
        for f in fields(cls):  # type: ignore[arg-type]
            if f.metadata.get(_REST):
                rest = f.name
                continue
            named.add(f.name)
            if f.name in doc:
                kwargs[f.name] = _load(hints[f.name], doc[f.name], f"{where}: {f.name}")
            elif f.default is MISSING and f.default_factory is MISSING:
                raise OmniSfmError(f"{where}: no {f.name!r} key")
        if rest is not None:
            kwargs[rest] = {k: v for k, v in doc.items() if k not in named}
        return cls(**kwargs)

    def write(self, path: Path | str) -> None:
        """Write :meth:`to_json` to ``path`` (atomically)."""
        atomic_write_text(Path(path), dumps_json(self.to_json()))

    @classmethod
    def read(cls: type[R], path: Path | str) -> R:
        """The report in the file ``path`` (one-line OmniSfmError if unreadable or malformed)."""
        return cls.from_json(read_json(Path(path), "report"), str(path))


def _input_path(inp: Any, key: str, folder: Path) -> Path | None:
    """The path ``inp[key]`` records (stored relative to ``folder`` or absolute), or None."""
    value = inp.get(key) if isinstance(inp, Mapping) else None
    return resolve_stored(value, folder) if isinstance(value, str) and value else None


@dataclass(frozen=True)
class FamilyReport(JsonReport):
    """An init report's ``parallel_family``: the tracks of the family of parallel lines and
    its unit direction in the world (NaN, and ``none`` saying why, when none was found)."""

    track_ids: list[int] | None = absent()
    direction: list[float] | None = absent()
    none: str | None = absent()
    other: dict[str, Any] = other_keys()


@dataclass(frozen=True)
class InitResiduals(JsonReport):
    """An init report's ``residuals``: RMS angle (deg) between observed and predicted line
    normals before and after the adjustment, and the noise it implies."""

    rms_initial_deg: float | None = absent()
    rms_final_deg: float | None = absent()
    noise_sigma_deg: float | None = absent()
    other: dict[str, Any] = other_keys()


@dataclass(frozen=True)
class InitMotion(JsonReport):
    """An init report's ``motion``, written only for a camera that only turned: ``kind``
    (``rotation only``), what ``translation`` is then, and ``why``."""

    kind: str
    translation: str | None = absent()
    why: str | None = absent()
    other: dict[str, Any] = other_keys()


@dataclass(frozen=True)
class InitSegment(JsonReport):
    """One of an init report's ``segments``: frames estimated apart from the main trajectory,
    in their own world and scale (``file``: their TUM file)."""

    file: str
    frames: list[int]
    """First and last frame."""
    num_frames_estimated: int
    world: str | None = absent()
    scale_convention: str | None = absent()
    residual_rms_deg: float | None = absent()
    other: dict[str, Any] = other_keys()


def _family_ids(fam: FamilyReport | None) -> list[int]:
    """``parallel_family.track_ids`` (empty when absent)."""
    return [] if fam is None else [int(i) for i in fam.track_ids or []]


class _StageInput:
    """What every stage folder's report says of its input (``input.images``, and the folder
    it was made from: ``input.init`` of refine, ``input.poses`` of dense)."""

    input: Any

    def images(self, folder: Path | str) -> Path | None:
        """The image folder or video the folder (``folder``, where the report lies) was made
        from, or None when the report records none."""
        return _input_path(self.input, "images", Path(folder))

    def previous_folder(self, folder: Path | str) -> Path | None:
        """The stage folder this one was made from (``input.init`` or ``input.poses``), or
        None when it records none (an init folder)."""
        return (_input_path(self.input, "init", Path(folder))
                or _input_path(self.input, "poses", Path(folder)))


@dataclass(frozen=True)
class StageReport(_StageInput, JsonReport):
    """Any stage folder's ``report.json`` (init, refine or dense), read for what every one may
    record: where the input is and (init) the parallel family."""

    input: dict[str, Any] = field(default_factory=dict)
    parallel_family: FamilyReport | None = absent()
    other: dict[str, Any] = other_keys()

    @property
    def family_direction(self) -> list[float] | None:
        """``parallel_family.direction``: the unit direction of the parallel family in the
        world, or None when the report has none."""
        d = None if self.parallel_family is None else self.parallel_family.direction
        return [float(x) for x in d] if isinstance(d, list) and len(d) == 3 else None

    @property
    def family_track_ids(self) -> list[int]:
        """``parallel_family.track_ids`` (empty when absent)."""
        return _family_ids(self.parallel_family)


@dataclass(frozen=True)
class InitReport(_StageInput, JsonReport):
    """An init folder's ``report.json`` (docs/formats.md), as the line-based estimator or an
    initializer plugin (:class:`PluginInitReport`) wrote it; the keys its readers use typed,
    the others in ``other``."""

    num_frames: int
    input: dict[str, Any] = field(default_factory=dict)
    initializer: str | None = absent()
    num_frames_estimated: int | None = absent()
    parallel_family: FamilyReport | None = absent()
    rejected_tracks: list[int] | None = absent()
    residuals: InitResiduals | None = absent()
    segments: list[InitSegment] | None = absent()
    motion: InitMotion | None = absent()
    """Only for a camera that only turned (docs/method.md §13)."""
    frames_uncertain: dict[str, str] | None = absent()
    uncertain_poses: str | None = absent()
    """Frame index -> why the data do not fix its pose (the global estimator's flags)."""
    other: dict[str, Any] = other_keys()

    @property
    def rotation_only(self) -> bool:
        """The camera only turned: positions are 0, the scale and the 3D lines undetermined."""
        return self.motion is not None

    @property
    def family_track_ids(self) -> list[int]:
        """``parallel_family.track_ids`` (empty when absent)."""
        return _family_ids(self.parallel_family)

    @property
    def rms_final_deg(self) -> float | None:
        """``residuals.rms_final_deg``: RMS angle between observed and predicted normals after
        refinement, or None when the report has none."""
        value = None if self.residuals is None else self.residuals.rms_final_deg
        return None if value is None else float(value)

    @property
    def segment_list(self) -> list[InitSegment]:
        """``segments`` (empty when the frames were estimated in one piece)."""
        return list(self.segments or [])


@dataclass(frozen=True)
class PluginInitReport(JsonReport):
    """``report.json`` of ``omni-sfm init --initializer NAME`` (docs/plugins.md)."""

    input: dict[str, Any]
    """``images``, ``camera``, ``timestamps`` (``seconds`` or ``frame index``)."""
    initializer: str
    status: str
    reason: str | None
    info: dict[str, Any]
    num_frames: int
    num_frames_estimated: int
    frames_not_estimated_names: list[str]
    wall_time_s: dict[str, float]
    scale_convention: str


@dataclass(frozen=True)
class ModelStatistics(JsonReport):
    """A COLMAP model's numbers as ``colmap model_analyzer`` gives them (refine's ``model``,
    ``triangulation`` and ``bundle_adjustment.after``)."""

    cameras: int
    images: int
    registered_images: int
    points: int
    observations: int
    mean_track_length: float
    mean_observations_per_image: float
    mean_reprojection_error_px: float
    other: dict[str, Any] = other_keys()


@dataclass(frozen=True)
class TriangulationReport(ModelStatistics):
    """Refine's ``triangulation``: the model triangulated on the input poses, and the seeded
    frames it posed again (their input disagreed with the points)."""

    frames_posed_again: list[str] | None = absent()


@dataclass(frozen=True)
class FeaturesReport(JsonReport):
    """Refine's ``features``: where they came from (``sift`` or ``klt``) and how many."""

    source: str
    extracted_images: int
    reused_images: int
    """Images whose features the database already held."""
    keypoints: int
    tracks: int | None = absent()
    """KLT tracks (``klt`` only)."""
    other: dict[str, Any] = other_keys()


@dataclass(frozen=True)
class MapperReport(JsonReport):
    """Refine's ``mapper``: how the frames without an input pose were registered. Either
    ``skipped`` (why), or ``registered`` / ``not_registered`` (frame names; the global mapper
    adds ``mapper``: ``global`` and its figures), then ``added_to_trajectory`` and
    ``timestamps`` (how they were placed)."""

    mapper: str | None = absent()
    skipped: str | None = absent()
    registered: list[str] | None = absent()
    not_registered: list[str] | None = absent()
    relative_poses: int | None = absent()
    rotation_averaging_converged: bool | None = absent()
    global_positioning_converged: bool | None = absent()
    observations_of_registered_frames: int | None = absent()
    added_to_trajectory: list[str] | None = absent()
    timestamps: str | None = absent()
    other: dict[str, Any] = other_keys()


@dataclass(frozen=True)
class AdjustmentRound(JsonReport):
    """One round of COLMAP's bundle adjustment and the filtering after it."""

    mean_reprojection_error_before_px: float
    mean_reprojection_error_after_px: float
    termination: str | None = absent()
    usable: bool | None = absent()
    removed_observations: int | None = absent()
    points: int | None = absent()
    other: dict[str, Any] = other_keys()


@dataclass(frozen=True)
class JointReport(JsonReport):
    """``bundle_adjustment.joint``: the joint adjustment of the init's lines and the model's
    points (docs/colmap.md): observations used and rejected, noise and RMS (deg), iterations,
    the evidence per frame, then the observations COLMAP's filter removed and the model
    ``after``."""

    line_observations: int
    point_observations: int
    point_observations_rejected: int | None = absent()
    lines_used: int | None = absent()
    points_used: int | None = absent()
    line_noise_deg: float | None = absent()
    point_noise_deg: float | None = absent()
    line_rms_deg: float | None = absent()
    point_rms_deg: float | None = absent()
    iterations: int | None = absent()
    evidence_per_frame: dict[str, Any] | None = absent()
    registered_frames: dict[str, Any] | None = absent()
    """The mapper's frames adjusted too: ``names`` and their ``evidence_per_frame``."""
    removed_observations: int | None = absent()
    after: ModelStatistics | None = absent()
    other: dict[str, Any] = other_keys()


@dataclass(frozen=True)
class BundleAdjustmentReport(JsonReport):
    """Refine's ``bundle_adjustment``: ``skipped`` (why), COLMAP's ``rounds`` (with
    ``held_fixed_frames`` and the model ``after``), or the ``joint`` adjustment's report."""

    skipped: str | None = absent()
    rounds: list[AdjustmentRound] | None = absent()
    held_fixed_frames: int | None = absent()
    after: ModelStatistics | None = absent()
    joint: JointReport | None = absent()
    other: dict[str, Any] = other_keys()


@dataclass(frozen=True)
class RefineCamera(JsonReport):
    """Refine's ``camera``: the init's camera model and the COLMAP model it was given as."""

    model: str
    colmap_model: str
    image_mirrored_for_colmap: bool
    other: dict[str, Any] = other_keys()


@dataclass(frozen=True)
class GuidedMatchingReport(JsonReport):
    """Refine's ``matching_guided``: pairs of posed frames matched along their poses, those
    written as verified, and the matches written."""

    pairs: int
    written: int
    matches: int
    other: dict[str, Any] = other_keys()


@dataclass(frozen=True)
class JointAdjustmentNote(JsonReport):
    """Refine's ``joint_adjustment``: why the joint adjustment of lines and points was
    ``skipped`` or how it ``failed``."""

    skipped: str | None = absent()
    failed: str | None = absent()
    other: dict[str, Any] = other_keys()


@dataclass(frozen=True)
class AlignmentReport(JsonReport):
    """Refine's ``alignment_to_input``: the similarity ``x_in = s R x_ref + t`` mapping the
    adjusted frames onto the input's."""

    rotation: Any
    """3 x 3 (a numpy array as built, lists as read back); also ``translation`` (3)."""
    translation: Any
    scale: float
    rotation_deg: float
    other: dict[str, Any] = other_keys()


@dataclass(frozen=True)
class FrameChange(JsonReport):
    """A frame's change from its input pose, and its support in the images."""

    rotation_deg: float
    position_fraction_of_path: float
    observations: int
    mean_reprojection_error_px: float
    other: dict[str, Any] = other_keys()


@dataclass(frozen=True)
class PoseChanges(JsonReport):
    """Refine's ``pose_changes``: the changes from the input poses of the frames refined (the
    large ones, which the frames' own observations back, by frame name)."""

    large_changes_backed_by_images: dict[str, FrameChange] | None = absent()
    rotation_deg_median: float | None = absent()
    rotation_deg_max: float | None = absent()
    position_fraction_of_path_median: float | None = absent()
    position_fraction_of_path_max: float | None = absent()
    other: dict[str, Any] = other_keys()


@dataclass(frozen=True)
class RefineReport(_StageInput, JsonReport):
    """A refine folder's ``report.json`` (docs/colmap.md), in the order written."""

    input: dict[str, Any]
    """``init``, ``images``, ``database``: stored paths."""
    camera: RefineCamera
    frames: dict[str, int]
    options: dict[str, Any]
    features: FeaturesReport
    matching: dict[str, int]
    triangulation: TriangulationReport
    mapper: MapperReport
    bundle_adjustment: BundleAdjustmentReport
    kept_input_for_all: str | None
    """Why every input pose was kept, or None."""
    refined_frames: int
    kept_frames: dict[str, str]
    """Frame name -> why its input pose was kept."""
    alignment_to_input: AlignmentReport | None
    pose_changes: PoseChanges | None
    model: ModelStatistics
    summary: str
    carried_from_input: list[str]
    trajectory_frames: int
    timings_s: dict[str, float]
    matching_guided: GuidedMatchingReport | None = absent()
    joint_adjustment: JointAdjustmentNote | None = absent()
    """Why the joint adjustment of lines and points was skipped or failed; absent otherwise."""
    lines3d: str | None = absent()

    _ORDER = ("input", "camera", "frames", "options", "features", "matching_guided",
              "matching", "triangulation", "mapper", "joint_adjustment", "bundle_adjustment",
              "kept_input_for_all", "refined_frames", "kept_frames", "alignment_to_input",
              "pose_changes", "model", "summary", "lines3d", "carried_from_input",
              "trajectory_frames", "timings_s")

    def to_json(self) -> dict[str, Any]:
        doc = super().to_json()
        return {k: doc[k] for k in self._ORDER if k in doc}

    @property
    def mapper_added(self) -> list[str]:
        """The frames without an input pose that COLMAP's mapper added to the trajectory."""
        return list(self.mapper.added_to_trajectory or [])

    @property
    def adjustment_rounds(self) -> list[AdjustmentRound]:
        """COLMAP's bundle adjustment rounds (empty when it did not run)."""
        return list(self.bundle_adjustment.rounds or [])

    @property
    def joint(self) -> JointReport | None:
        """The joint adjustment's report when it ran, else None."""
        return self.bundle_adjustment.joint


@dataclass(frozen=True)
class ScaleReport(JsonReport):
    """Dense's ``scale``: where the output unit comes from (``source``: ``known_distance``,
    ``camera_height`` or ``poses``), the source's figures, and ``factor``, the output units per
    pose unit."""

    source: str
    unit: str
    first_last_pose_units: float | None = absent()
    known_distance: float | None = absent()
    camera_height: float | None = absent()
    other: dict[str, Any] = other_keys()
    """The floor fit's figures (``camera_height``)."""
    factor: float = field(kw_only=True)


@dataclass(frozen=True)
class CalibrationTrial(JsonReport):
    """One frame offset the baseline calibration tried."""

    offset: int
    baseline: float
    median_disparity_px: float | None
    depth_share: float
    other: dict[str, Any] = other_keys()


@dataclass(frozen=True)
class CalibrationReport(JsonReport):
    """Dense's ``calibration``: the frame and the frame offset that set the stereo baseline."""

    frame: int
    frame_offset: int
    trials: list[CalibrationTrial]
    other: dict[str, Any] = other_keys()


@dataclass(frozen=True)
class ViewsReport(JsonReport):
    """Dense's ``views``: the virtual pinhole views stereo runs on."""

    focal_px: float
    width: int
    height: int
    per_pair: int
    num_disparities: int
    other: dict[str, Any] = other_keys()


@dataclass(frozen=True)
class PairPoseSummary(JsonReport):
    """Dense's ``pair_pose``: the relative-pose check of the stereo pairs over all keyframes."""

    enabled: bool
    pairs: int
    corrected: int
    median_rotation_change_deg: float | None
    """None when no pair was corrected."""
    other: dict[str, Any] = other_keys()


@dataclass(frozen=True)
class PairPoseCheck(JsonReport):
    """The relative-pose check of one stereo pair of a keyframe."""

    corrected: bool
    inliers: int
    rotation_change_deg: float
    """Estimate minus given (NaN without an estimate); also ``direction_change_deg``."""
    direction_change_deg: float
    other: dict[str, Any] = other_keys()


@dataclass(frozen=True)
class DenseFrame(JsonReport):
    """One keyframe of dense's ``frames``."""

    frame: int
    timestamp: float
    image: str
    sources: list[int]
    """The frames it was matched with."""
    baselines: list[float]
    depth_share: float
    view_share: float | None = absent()
    view_pixels: int | None = absent()
    depth_pixels: int | None = absent()
    seconds_depth: float | None = absent()
    seconds_fusion: float | None = absent()
    pair_pose: list[PairPoseCheck] | None = absent()
    other: dict[str, Any] = other_keys()


@dataclass(frozen=True)
class BackendReport(JsonReport):
    """Dense's ``backend``: what computed the depths and the fusion."""

    stereo: str
    fusion: str
    pycolmap_cuda: bool | None = absent()
    note: str | None = absent()
    other: dict[str, Any] = other_keys()


@dataclass(frozen=True)
class DenseReport(_StageInput, JsonReport):
    """A dense folder's ``report.json`` (docs/dense.md), in the order written."""

    scale: ScaleReport
    median_depth: float
    stereo_baseline: float
    voxel_size: float
    calibration: CalibrationReport
    views: ViewsReport
    keyframe_step: int
    pair_pose: PairPoseSummary
    num_keyframes: int
    num_points: int
    num_triangles: int
    depth_share: dict[str, float]
    """``median``, ``min``, ``max`` over the keyframes."""
    seconds: dict[str, float]
    frames: list[DenseFrame]
    """One entry per keyframe."""
    warnings: list[str]
    backend: BackendReport
    note: str
    input: dict[str, Any] = field(default_factory=dict)
    """``poses``, ``images``: stored paths (written first; empty before the map is written)."""

    def to_json(self) -> dict[str, Any]:
        doc = super().to_json()
        inp = doc.pop("input")
        return {"input": inp, **doc} if inp else doc


@dataclass(frozen=True)
class ExportWorld(JsonReport):
    """An export's ``world``: whether the folder's world was ``turned`` gravity-up, the 4 x 4
    ``export_from_world`` (x_export = R x_world + t), the vertical found in the folder's world
    (null when not turned), ``how`` it was found and the ``convention``."""

    turned: bool
    export_from_world: list[list[float]]
    vertical_in_world: list[float] | None = None
    how: str | None = absent()
    convention: str | None = absent()
    other: dict[str, Any] = other_keys()


@dataclass(frozen=True)
class ExportReport(JsonReport):
    """An export's ``report.json`` (docs/formats.md, "Exports")."""

    omni_sfm_version: str
    format: str
    input: str
    """The exported folder (stored path)."""
    num_poses: int
    world: ExportWorld
    camera_model: str
    written: dict[str, Any] = other_keys()
    """What the format's writer wrote (files, image counts, views), as the writer names it."""
    seconds: float = 0.0

    @property
    def turned(self) -> bool:
        """The world was turned gravity-up."""
        return bool(self.world.turned)

    @property
    def num_images(self) -> int | None:
        """Images written, for formats that write images."""
        n = self.written.get("num_images")
        return None if n is None else int(n)


@dataclass(frozen=True)
class CompareEntry(JsonReport):
    """One initializer's entry of ``results.json`` (docs/comparison.md)."""

    status: str
    """``ok`` or ``failed``."""
    trajectory: str | None
    """``trajectories/NAME.tum``, or None when it registered nothing."""
    registered: float
    rot_max_deg: float | None
    rot_mean_deg: float | None
    ate_rel: float | None
    rpe: float | None
    rpe_rot_deg: float | None
    step_error_after_alignment: float | None
    frames_compared: int
    frames_registered: int
    time_s: float
    reason: str | None = absent()
    info: dict[str, Any] | None = absent()

    _ORDER = ("status", "reason", "trajectory", "registered", "rot_max_deg", "rot_mean_deg",
              "ate_rel", "rpe", "rpe_rot_deg", "step_error_after_alignment",
              "frames_compared", "frames_registered", "time_s", "info")

    def to_json(self) -> dict[str, Any]:
        doc = super().to_json()
        return {k: doc[k] for k in self._ORDER if k in doc}


@dataclass(frozen=True)
class CompareSequence(JsonReport):
    """``results.json``'s ``sequence``: its name, number of frames and camera model."""

    name: str | None = absent()
    frames: int | None = absent()
    camera: str | None = absent()
    other: dict[str, Any] = other_keys()


@dataclass(frozen=True)
class CompareResults(JsonReport):
    """``results.json`` of ``omni-sfm compare``: an entry per initializer, and the sequence
    (``name``, ``frames``, ``camera``)."""

    initializers: dict[str, CompareEntry]
    sequence: CompareSequence = field(default_factory=CompareSequence)

    @classmethod
    def from_json(cls, doc: Any, where: str = "results") -> CompareResults:
        if not isinstance(doc, Mapping) or not isinstance(doc.get("initializers"), Mapping):
            raise OmniSfmError(f"{where}: no 'initializers' object")
        return super().from_json(doc, where)


@dataclass(frozen=True)
class TrackPose(JsonReport):
    """A pose in a line of ``frames.jsonl`` (docs/track.md): world_from_cam as the camera
    centre and the rotation's quaternion (x, y, z, w), None where the frame has none."""

    frame: int
    timestamp: float
    position: list[float] | None
    quaternion_xyzw: list[float] | None


@dataclass(frozen=True)
class TrackFrame(JsonReport):
    """One line of ``omni-sfm track``'s ``frames.jsonl`` (the same as ``--stream`` prints;
    written by ``TrackedPose.to_json`` of :mod:`omni_sfm.estimate.online`, docs/track.md)."""

    frame: int
    timestamp: float
    position: list[float] | None
    quaternion_xyzw: list[float] | None
    status: str
    """``initialising``, ``tracking``, ``rotation-only``, ``lost`` or ``relocalised``."""
    world: int
    """Which start the pose is in (0: the first; +1 with each restart after a loss)."""
    lines: int
    lines_known: int
    latency_ms: float
    reason: str | None
    start_poses: list[TrackPose]
    """Where a start succeeded, the poses of the buffered frames it solved."""

    @property
    def has_pose(self) -> bool:
        """A full pose (rotation and position)."""
        return self.position is not None and self.quaternion_xyzw is not None


def read_track_frames(path: Path | str) -> list[TrackFrame]:
    """Every line of a ``frames.jsonl`` (one-line OmniSfmError naming the line if one is not a
    frame)."""
    import json

    out = []
    for k, text in enumerate(Path(path).read_text(encoding="utf-8").splitlines(), 1):
        if not text.strip():
            continue
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as exc:
            raise OmniSfmError(f"{path}:{k}: not JSON ({exc.msg})") from None
        out.append(TrackFrame.from_json(doc, f"{path}:{k}"))
    return out
