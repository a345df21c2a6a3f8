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
same two methods. Every key omni-sfm writes is a field, so a file read and written again is the
same to the byte; a key no field names (another writer's) is kept in the section's ``other``
and written back after its fields. Sections whose content is another module's record (the
front end's per-frame columns, a view layout) stay JSON objects.
:meth:`JsonReport.to_json` gives the document, :meth:`JsonReport.from_json` reads one back (a
one-line OmniSfmError when a required key is missing), :meth:`JsonReport.write` and
:meth:`JsonReport.read` go through files (atomic write).
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
    if value is None or hint is Any or isinstance(value, JsonReport):
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


@dataclass(frozen=True)
class JsonReport:
    """JSON form of a frozen dataclass report (the base of every report and section; see the
    module docstring).

    A field whose type is a report (``X``, ``X | None``, ``list[X]``, ``dict[str, X]``) is
    written as that report's document and read back with that report's :meth:`from_json`, so
    a section typed as its own dataclass needs no (de)serialisation of its own."""

    other: dict[str, Any] = field(default_factory=dict, kw_only=True, metadata={_REST: True})
    """The keys of a document read that no field names, written back after the fields: a
    reader's tolerance of another writer's (or a newer version's) keys. omni-sfm's own
    writers write none (:func:`undeclared_keys`; tests/helpers.py checks the files they
    write)."""

    def to_json(self) -> dict[str, Any]:
        """The JSON document: the fields in order, their keys the fields' names, then the
        keys of ``other``."""
        out: dict[str, Any] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if not f.metadata.get(_REST) and (value is not None or not f.metadata.get(_OMIT)):
                out[f.name] = _dump(value)
        out.update(self.other)
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
        for f in fields(cls):
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


def undeclared_keys(value: Any, where: str = "") -> list[str]:
    """The keys no field names (those kept in an ``other``) in ``value``, a report (nested
    reports, lists and dicts of them searched too), each as its path (``mapper.why``,
    ``frames[2].note``). Empty for every report omni-sfm writes."""
    out: list[str] = []
    if isinstance(value, JsonReport):
        for f in fields(value):
            v = getattr(value, f.name)
            if f.metadata.get(_REST):
                out += [f"{where}{k}" for k in v]
            else:
                out += undeclared_keys(v, f"{where}{f.name}.")
    elif isinstance(value, list):
        for k, v in enumerate(value):
            out += undeclared_keys(v, f"{where.rstrip('.')}[{k}].")
    elif isinstance(value, dict):
        for k, v in value.items():
            out += undeclared_keys(v, f"{where}{k}.")
    return out


@dataclass(frozen=True)
class InitInput(JsonReport):
    """An init report's ``input``: the frames (``images``), the ``camera`` (its file, else the
    model's name), the user's ``mask`` (null when none), ``start``/``end``/``step`` (``end``
    null: to the last frame) and ``timestamps`` (``seconds`` for a video, ``frame index`` for
    an image folder); of ``init --tracks``, the ``tracks`` file alone. Paths are stored paths
    (relative to the folder when inside it, else absolute)."""

    images: str | None = None
    camera: str | None = None
    mask: str | None = None
    start: int | None = None
    end: int | None = None
    step: int | None = None
    timestamps: str | None = None
    tracks: str | None = absent()

    def to_json(self) -> dict[str, Any]:
        doc = super().to_json()
        if self.tracks is None:
            return doc
        return {k: v for k, v in doc.items() if v is not None or k in self.other}

    @property
    def previous(self) -> str | None:
        """An init folder is made from no other folder."""
        return None


@dataclass(frozen=True)
class PluginInitInput(JsonReport):
    """``input`` of ``init --initializer NAME``: the frames (``images``), the ``camera`` (its
    file, else the model's name), ``timestamps`` (``seconds`` or ``frame index``)."""

    images: str
    camera: str
    timestamps: str

    @property
    def previous(self) -> str | None:
        """An init folder is made from no other folder."""
        return None


@dataclass(frozen=True)
class RefineInput(JsonReport):
    """Refine's ``input``: the ``init`` folder, the ``images`` and the COLMAP ``database``
    (stored paths)."""

    init: str
    images: str
    database: str

    @property
    def previous(self) -> str | None:
        """The folder refined: ``init``."""
        return self.init


@dataclass(frozen=True)
class DenseInputRecord(JsonReport):
    """Dense's ``input``: the folder of the ``poses`` (null when they were given otherwise)
    and the ``images`` (stored paths)."""

    poses: str | None
    images: str

    @property
    def previous(self) -> str | None:
        """The folder of the poses: ``poses``."""
        return self.poses


@dataclass(frozen=True)
class StageInput(JsonReport):
    """Any stage report's ``input``, read for what every one may record: the ``images`` and
    the folder it was made from (``init`` of refine, ``poses`` of dense); the stage's other
    input keys in ``other``."""

    images: str | None = absent()
    init: str | None = absent()
    poses: str | None = absent()

    @property
    def previous(self) -> str | None:
        """The folder it was made from (``init`` or ``poses``), or None."""
        return self.init or self.poses


def _stored(value: str | None, folder: Path) -> Path | None:
    """The path a report stores (relative to ``folder`` or absolute), or None."""
    return resolve_stored(value, folder) if isinstance(value, str) and value else None


@dataclass(frozen=True)
class FamilyReport(JsonReport):
    """An init report's ``parallel_family``: the tracks of the family of parallel lines and
    its unit direction in the world (NaN, and ``none`` saying why, when none was found)."""

    track_ids: list[int] | None = absent()
    direction: list[float] | None = absent()
    none: str | None = absent()


@dataclass(frozen=True)
class InitResiduals(JsonReport):
    """An init report's ``residuals``: RMS angle (deg) between observed and predicted line
    normals before and after the adjustment, and the noise it implies."""

    rms_initial_deg: float | None = absent()
    rms_final_deg: float | None = absent()
    noise_sigma_deg: float | None = absent()


@dataclass(frozen=True)
class InitMotion(JsonReport):
    """An init report's ``motion``, written only for a camera that only turned: ``kind``
    (``rotation only``), what ``translation`` is then, and ``why``."""

    kind: str
    translation: str | None = absent()
    why: str | None = absent()


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


def _family_ids(fam: FamilyReport | None) -> list[int]:
    """``parallel_family.track_ids`` (empty when absent)."""
    return [] if fam is None else [int(i) for i in fam.track_ids or []]


class _StageInput:
    """What every stage folder's report says of its input (``input.images``, and the folder
    it was made from: ``input.init`` of refine, ``input.poses`` of dense)."""

    input: InitInput | PluginInitInput | RefineInput | DenseInputRecord | StageInput | None

    def images(self, folder: Path | str) -> Path | None:
        """The image folder or video the folder (``folder``, where the report lies) was made
        from, or None when the report records none."""
        return None if self.input is None else _stored(self.input.images, Path(folder))

    def previous_folder(self, folder: Path | str) -> Path | None:
        """The stage folder this one was made from (``input.init`` or ``input.poses``), or
        None when it records none (an init folder)."""
        return None if self.input is None else _stored(self.input.previous, Path(folder))


@dataclass(frozen=True)
class StageReport(_StageInput, JsonReport):
    """Any stage folder's ``report.json`` (init, refine or dense), read for what every one may
    record: where the input is and (init) the parallel family."""

    input: StageInput = field(default_factory=StageInput)
    parallel_family: FamilyReport | None = absent()
    rig: RigScaleRecord | None = absent()
    """A rig camera's poses: their metric scale (init, dense)."""

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
class FamiliesFound(JsonReport):
    """An init report's ``parallel_families``: the ``sizes`` of the parallel families found
    (tracks, largest first: the windows use the first) and the windows solved with another
    family because the first was degenerate there (``windows_with_another_family``, with the
    reason)."""

    sizes: list[int]
    windows_with_another_family: list[str]


@dataclass(frozen=True)
class CameraCheck(JsonReport):
    """An init report's ``camera_check``: whether the camera model fits the frames (``ok``,
    the ``message``) and its figures (fractions, null where too few lines or segments to
    tell; ``median_residual_px``; the counts of ``long_lines`` and ``image_segments``)."""

    ok: bool
    message: str
    bent_lines: float | None = None
    straight_in_image_curved_on_sphere: float | None = None
    empty_valid: float | None = None
    moving_outside: float | None = None
    median_residual_px: float | None = None
    long_lines: float | None = None
    image_segments: float | None = None


@dataclass(frozen=True)
class AutoMaskReport(JsonReport):
    """An init report's ``auto_mask``: whether the automatic mask was ``applied``, the
    fractions of the image it masks, of edges that stayed put and of edges that wobbled a few
    pixels with the camera (absent when there were too few frames to tell), and the
    ``reason``."""

    applied: bool
    masked_fraction: float | None = absent()
    static_edge_fraction: float | None = absent()
    wobbling_edge_fraction: float | None = absent()
    reason: str | None = absent()


@dataclass(frozen=True, kw_only=True)
class EstimatorStep(JsonReport):
    """One of the global estimator's ``steps`` (docs/estimator.md), as far as it applies: the
    ``step``; the sizes of the parallel families, the ``start`` the rotations were kept from
    (``anchored`` or ``windows``), the number of ``directions`` or ``world_directions`` shared;
    the solver's ``iterations``, the ``outlier_tracks`` it rejected, the robust noise estimate
    ``sigma_deg`` and the final RMS residual ``rms_final_deg``; the tracks ``joined`` to an
    earlier track of their line on a revisit."""

    step: str
    families: list[int] | None = absent()
    start: str | None = absent()
    directions: int | None = absent()
    world_directions: int | None = absent()
    iterations: int | None = absent()
    outlier_tracks: int | None = absent()
    sigma_deg: float | None = absent()
    rms_final_deg: float | None = absent()
    joined: int | None = absent()


@dataclass(frozen=True, kw_only=True)
class PoseSpreadRecord(JsonReport):
    """An init report's ``pose_spread`` (the global estimator's): per frame (by index), the RMS
    error that the adjustment's covariance expects of its rotation (``rotation_deg``) and of
    its centre (``position_pct_of_path``), the frames not flagged aligned to the truth
    (docs/estimator.md); null for a frame not posed or left free (``frames_uncertain`` says
    which)."""

    rotation_deg: list[float | None]
    position_pct_of_path: list[float | None]


@dataclass(frozen=True, kw_only=True)
class RigScaleRecord(JsonReport):
    """An init report's ``rig`` (a rig of lenses, docs/estimator.md "Rigs"): the metres that
    one unit of the trajectory spans, the metric scale the baseline between the lenses fixes;
    where the lines are too far for it, a rough one (the offsets too small to matter either),
    or null; ``note`` says which, ``fixed`` whether the baseline fixes it (None where the
    writer does not say: only a fixed scale makes a dense map metric)."""

    metres_per_unit: float | None
    note: str
    fixed: bool | None = absent()


@dataclass(frozen=True, kw_only=True)
class AttemptRecord(JsonReport):
    """One of an init report's ``attempts`` (docs/estimator.md, "Strategies and attempts"):
    the ``strategy``, the first and last frame it ran on (whole-sequence indices; absent for
    the whole input), its ``result`` (``kept``, ``rejected``, ``failed``, ``skipped``), the RMS
    angle between observed and predicted normals at its solution, ``why``; ``family`` for the
    paper's window solved with another family."""

    strategy: str
    frames: list[int] | None = absent()
    result: str
    cost_rms_deg: float | None = absent()
    why: str | None = absent()
    family: int | None = absent()


@dataclass(frozen=True)
class SkippedFrame(JsonReport):
    """A frame the front end skipped (``front_end.frames_skipped_reasons``): its source index,
    why, and (``init --images``) its image name."""

    frame: int
    reason: str
    name: str | None = absent()


@dataclass(frozen=True)
class TrackLengths(JsonReport):
    """``front_end.track_length_frames``: the tracks' lengths in frames."""

    median: float
    min: int
    max: int


@dataclass(frozen=True)
class FrontEndSummary(JsonReport):
    """An init report's ``front_end``: the line front end's counts and median timings
    (``FrontEndResult.summary``): frames, the frames skipped and why, the pixels searched,
    tracks and observations, track lengths, lines per frame, segments rejected, lines
    continued, tracks started and revived, and the median per-frame and total timings (ms) of
    each step."""

    frames: int
    frames_skipped: list[int]
    frames_skipped_reasons: list[SkippedFrame]
    valid_pixels: int
    tracks: int
    observations: int
    track_length_frames: TrackLengths
    lines_per_frame_median: float
    lines_extracted_total: int
    segments_rejected_total: int
    lines_continued_per_frame_median: float
    tracks_started_total: int
    tracks_revived_total: int
    timings_ms_per_frame_median: dict[str, float]
    timings_ms_total: dict[str, float]


@dataclass(frozen=True, kw_only=True)
class InitReport(_StageInput, JsonReport):
    """An init folder's ``report.json`` as the line-based estimator writes it (docs/formats.md):
    the estimator's keys (it builds this report), then ``uncertain_poses`` and what ``init``
    adds (``input`` and, for frames, the front end's figures). Every key is a field, in the
    order written; a key absent from a file (an older or another writer's) is None. A plugin's
    init folder has :class:`PluginInitReport`."""

    omni_sfm_version: str | None = absent()
    initializer: str | None = absent()
    num_frames: int
    num_frames_estimated: int | None = absent()
    frames_not_estimated: list[int] | None = absent()
    num_tracks: int | None = absent()
    num_observations: int | None = absent()
    num_tracks_used: int | None = absent()
    parallel_family: FamilyReport | None = absent()
    rejected_tracks: list[int] | None = absent()
    unused_tracks: list[int] | None = absent()
    windows: list[list[int]] | None = absent()
    """First and last frame of each window of the paper's method."""
    world: str | None = absent()
    scale_convention: str | None = absent()
    reflection_ambiguity: str | None = absent()
    timings_ms: dict[str, float] | None = absent()
    residuals: InitResiduals | None = absent()
    estimator: str | None = absent()
    """The estimator that ran: ``paper`` or ``global``."""
    estimator_choice: str | None = absent()
    """Why that one: ``asked for`` (``--estimator paper|global``) or what ``auto`` saw."""
    reflection: str | None = absent()
    steps: list[EstimatorStep] | None = absent()
    """The global estimator's steps (docs/estimator.md)."""
    world_directions: list[list[float]] | None = absent()
    parallel_families: FamiliesFound | None = absent()
    motion: InitMotion | None = absent()
    """Only for a camera that only turned (docs/method.md §13)."""
    frames_not_estimated_reasons: dict[str, str] | None = absent()
    frames_uncertain: dict[str, str] | None = absent()
    """Frame index -> why the data do not fix its pose (the global estimator's flags)."""
    pose_spread: PoseSpreadRecord | None = absent()
    """How well the data fix each frame's pose (the global estimator's)."""
    rig: RigScaleRecord | None = absent()
    """The metric scale of a rig of lenses (their offsets): :class:`RigScaleRecord`."""
    attempts: list[AttemptRecord] | None = absent()
    """Every strategy tried, in the order it ran."""
    segments: list[InitSegment] | None = absent()
    uncertain_poses: str | None = absent()
    input: InitInput | None = absent()
    front_end: FrontEndSummary | None = absent()
    front_end_per_frame: dict[str, list[Any]] | None = absent()
    """The front end's per-frame columns (``FrontEndResult.per_frame``)."""
    frames_not_estimated_names: list[str] | None = absent()
    wall_time_s: dict[str, float] | None = absent()
    camera_check: CameraCheck | None = absent()
    auto_mask: AutoMaskReport | None = absent()
    camera_fixed_tracks: list[int] | None = absent()
    warnings: list[str] | None = absent()

    def to_json(self) -> dict[str, Any]:
        doc = super().to_json()
        if self.motion is None or "reflection" not in doc:
            return doc
        # the rotation-only fit's report has its reflection note after the frames' reasons
        keys = [k for k in doc if k != "reflection"]
        at = keys.index("frames_not_estimated_reasons") + 1 \
            if "frames_not_estimated_reasons" in keys else len(keys)
        keys.insert(at, "reflection")
        return {k: doc[k] for k in keys}

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
class InitializerInfo(JsonReport):
    """An initializer's ``info`` (``init --initializer``'s report, ``compare``'s entries): the
    figures omni-sfm's initializers give, each absent where the initializer has none.
    ``five-point``/``upright`` chain relative poses (``observations``, ``tracks``,
    ``median_inliers_per_pair``, ``stride``, ``features``, ``ransac_max_error_rad``; upright
    also ``family_tracks``, ``frames_without_vpv``); ``lines``: ``tracks``,
    ``parallel_tracks``, ``residual_rms_deg``, ``reflection``; ``colmap``: ``features``,
    ``verified_pairs``, ``models``, ``mapper``, ``database_s``, ``mapper_s``, ``points3D``,
    ``registered`` (``metres_per_unit`` for a rig camera); ``lines+refine``: ``init_frames``,
    ``refined_frames``, ``added_by_mapper``, ``kept_input_for_all``."""

    observations: int | None = absent()
    tracks: int | None = absent()
    parallel_tracks: int | None = absent()
    residual_rms_deg: float | None = absent()
    reflection: str | None = absent()
    median_inliers_per_pair: float | None = absent()
    stride: int | None = absent()
    features: str | None = absent()
    ransac_max_error_rad: float | None = absent()
    family_tracks: int | None = absent()
    frames_without_vpv: int | None = absent()
    verified_pairs: int | None = absent()
    models: int | None = absent()
    mapper: str | None = absent()
    database_s: float | None = absent()
    mapper_s: float | None = absent()
    points3D: int | None = absent()
    registered: int | None = absent()
    init_frames: int | None = absent()
    refined_frames: int | None = absent()
    added_by_mapper: int | None = absent()
    kept_input_for_all: str | None = absent()
    """Why refine kept every input pose (absent when it refined some)."""
    metres_per_unit: float | None = absent()
    """``colmap`` of a rig camera: the metres one unit of its trajectory spans (1: the lens
    offsets, held in metres, fix its scale)."""


@dataclass(frozen=True)
class PluginInitReport(JsonReport):
    """``report.json`` of ``omni-sfm init --initializer NAME`` (docs/plugins.md)."""

    input: PluginInitInput
    initializer: str
    status: str
    reason: str | None
    info: InitializerInfo
    num_frames: int
    num_frames_estimated: int
    frames_not_estimated_names: list[str]
    wall_time_s: dict[str, float]
    scale_convention: str
    rig: RigScaleRecord | None = absent()
    """A rig camera's poses: their metric scale, where the initializer gives its poses in
    metres (``info.metres_per_unit``)."""


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


@dataclass(frozen=True)
class AdjustmentRound(JsonReport):
    """One round of COLMAP's bundle adjustment and the filtering after it."""

    mean_reprojection_error_before_px: float
    mean_reprojection_error_after_px: float
    termination: str | None = absent()
    usable: bool | None = absent()
    removed_observations: int | None = absent()
    points: int | None = absent()


@dataclass(frozen=True)
class FrameEvidence(JsonReport):
    """The joint adjustment's evidence per frame (lists over the frames, in order): line and
    point observations used, the lines' share of each frame's rotation and position
    information, and how far the adjustment moved the frame (deg, path units); null where a
    figure is undefined."""

    lines: list[int]
    points: list[int]
    line_share_rotation: list[float | None]
    line_share_position: list[float | None]
    rotation_change_deg: list[float | None]
    position_change: list[float | None]


@dataclass(frozen=True)
class RegisteredFrames(JsonReport):
    """``bundle_adjustment.joint.registered_frames``: the frames COLMAP's mapper registered,
    adjusted with the others: their ``names`` and ``evidence_per_frame``."""

    names: list[str]
    evidence_per_frame: FrameEvidence


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
    evidence_per_frame: FrameEvidence | None = absent()
    """Of the input's frames, in the trajectory's order."""
    registered_frames: RegisteredFrames | None = absent()
    """The mapper's frames adjusted too."""
    removed_observations: int | None = absent()
    after: ModelStatistics | None = absent()


@dataclass(frozen=True)
class BundleAdjustmentReport(JsonReport):
    """Refine's ``bundle_adjustment``: ``skipped`` (why), COLMAP's ``rounds`` (with
    ``held_fixed_frames`` and the model ``after``), or the ``joint`` adjustment's report."""

    skipped: str | None = absent()
    rounds: list[AdjustmentRound] | None = absent()
    held_fixed_frames: int | None = absent()
    after: ModelStatistics | None = absent()
    joint: JointReport | None = absent()


@dataclass(frozen=True)
class RefineCamera(JsonReport):
    """Refine's ``camera``: the init's camera model and the COLMAP model it was given as."""

    model: str
    colmap_model: str
    image_mirrored_for_colmap: bool


@dataclass(frozen=True)
class GuidedMatchingReport(JsonReport):
    """Refine's ``matching_guided``: pairs of posed frames matched along their poses, those
    written as verified, and the matches written."""

    pairs: int
    written: int
    matches: int


@dataclass(frozen=True)
class JointAdjustmentNote(JsonReport):
    """Refine's ``joint_adjustment``: why the joint adjustment of lines and points was
    ``skipped`` or how it ``failed``."""

    skipped: str | None = absent()
    failed: str | None = absent()


@dataclass(frozen=True)
class AlignmentReport(JsonReport):
    """Refine's ``alignment_to_input``: the similarity ``x_in = s R x_ref + t`` mapping the
    adjusted frames onto the input's."""

    rotation: Any
    """3 x 3 (a numpy array as built, lists as read back); also ``translation`` (3)."""
    translation: Any
    scale: float
    rotation_deg: float


@dataclass(frozen=True)
class FrameChange(JsonReport):
    """A frame's change from its input pose, and its support in the images."""

    rotation_deg: float
    position_fraction_of_path: float
    observations: int
    mean_reprojection_error_px: float


@dataclass(frozen=True)
class PoseChanges(JsonReport):
    """Refine's ``pose_changes``: the changes from the input poses of the frames refined (the
    large ones, which the frames' own observations back, by frame name)."""

    large_changes_backed_by_images: dict[str, FrameChange] | None = absent()
    rotation_deg_median: float | None = absent()
    rotation_deg_max: float | None = absent()
    position_fraction_of_path_median: float | None = absent()
    position_fraction_of_path_max: float | None = absent()


@dataclass(frozen=True)
class RefineSettings(JsonReport):
    """Refine's ``options``: the :class:`omni_sfm.refine.pipeline.RefineOptions` it ran with,
    field by field (the same names, in the same order; a test keeps the two alike); an option
    a folder's report lacks (an older writer's) is None."""

    features: str | None = absent()
    max_features: int | None = absent()
    guided_matching: bool | None = absent()
    max_corners: int | None = absent()
    klt_verify: bool | None = absent()
    overlap: int | None = absent()
    mask_erosion_px: int | None = absent()
    num_threads: int | None = absent()
    register_missing: bool | None = absent()
    mapper: str | None = absent()
    ba_rounds: int | None = absent()
    ba_max_iterations: int | None = absent()
    prior_position_sigma: float | None = absent()
    loss_scale_px: float | None = absent()
    max_reprojection_error_px: float | None = absent()
    min_triangulation_angle_deg: float | None = absent()
    min_points: int | None = absent()
    min_points_per_frame: float | None = absent()
    min_observations: int | None = absent()
    max_rotation_change_deg: float | None = absent()
    max_position_change: float | None = absent()
    max_frame_error_px: float | None = absent()
    max_mean_reprojection_error_px: float | None = absent()
    adjustment: str | None = absent()
    text: bool | None = absent()


@dataclass(frozen=True)
class RefineReport(_StageInput, JsonReport):
    """A refine folder's ``report.json`` (docs/colmap.md), in the order written."""

    input: RefineInput
    camera: RefineCamera
    frames: dict[str, int]
    """``input_poses``, ``images_in_folder``, ``unposed_in_folder``."""
    options: RefineSettings
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
    rig: RigScaleRecord | None = absent()
    """A rig camera: the metres of one unit of this folder's poses (its lens offsets)."""

    _ORDER = ("input", "camera", "frames", "options", "features", "matching_guided",
              "matching", "triangulation", "mapper", "joint_adjustment", "bundle_adjustment",
              "kept_input_for_all", "refined_frames", "kept_frames", "alignment_to_input",
              "pose_changes", "model", "summary", "lines3d", "rig", "carried_from_input",
              "trajectory_frames", "timings_s")

    def to_json(self) -> dict[str, Any]:
        doc = super().to_json()
        return {**{k: doc[k] for k in self._ORDER if k in doc}, **self.other}

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
    ``camera_height``, ``rig``: a rig's lens offsets, or ``poses``), the source's figures, and
    ``factor``, the output units per pose unit."""

    source: str
    unit: str
    first_last_pose_units: float | None = absent()
    known_distance: float | None = absent()
    camera_height: float | None = absent()
    floor_points: int | None = absent()
    """``camera_height``: the floor's points, its tilt from the cameras' up axis, and the
    cameras' height above it in pose units."""
    floor_tilt_deg: float | None = absent()
    camera_height_pose_units: float | None = absent()
    factor: float = field(kw_only=True)


@dataclass(frozen=True)
class CalibrationTrial(JsonReport):
    """One frame offset the baseline calibration tried."""

    offset: int
    baseline: float
    median_disparity_px: float | None
    depth_share: float


@dataclass(frozen=True)
class CalibrationReport(JsonReport):
    """Dense's ``calibration``: the frame and the frame offset that set the stereo baseline."""

    frame: int
    frame_offset: int
    trials: list[CalibrationTrial]


@dataclass(frozen=True)
class ViewsReport(JsonReport):
    """Dense's ``views``: the virtual pinhole views stereo runs on."""

    focal_px: float
    width: int
    height: int
    per_pair: int
    num_disparities: int


@dataclass(frozen=True)
class PairPoseSummary(JsonReport):
    """Dense's ``pair_pose``: the relative-pose check of the stereo pairs over all keyframes."""

    enabled: bool
    pairs: int
    corrected: int
    median_rotation_change_deg: float | None
    """None when no pair was corrected."""


@dataclass(frozen=True)
class PairPoseCheck(JsonReport):
    """The relative-pose check of one stereo pair of a keyframe."""

    corrected: bool
    inliers: int
    rotation_change_deg: float
    """Estimate minus given (NaN without an estimate); also ``direction_change_deg``."""
    direction_change_deg: float


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


@dataclass(frozen=True)
class BackendReport(JsonReport):
    """Dense's ``backend``: what computed the depths and the fusion."""

    stereo: str
    fusion: str
    pycolmap_cuda: bool | None = absent()
    note: str | None = absent()


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
    rig: RigScaleRecord | None = absent()
    """A rig camera: the metres of one unit of this folder's poses (its lens offsets)."""
    input: DenseInputRecord | None = absent()
    """Written first; None before the map is written."""

    def to_json(self) -> dict[str, Any]:
        doc = super().to_json()
        return {"input": doc.pop("input"), **doc} if "input" in doc else doc


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


@dataclass(frozen=True)
class ExportWritten(JsonReport):
    """What an export's writer wrote, as its keys in ``report.json`` (between
    ``camera_model`` and ``seconds``); the base of each format's class, read for another
    format's keys (all in ``other``)."""

    @property
    def images_written(self) -> int | None:
        """Images written, for formats that write images."""
        return None


@dataclass(frozen=True)
class TrajectoryWritten(ExportWritten):
    """``tum`` / ``kitti``: the ``files`` written and the camera frame the poses refer to."""

    files: list[str] = field(default_factory=list, kw_only=True)
    camera_frame: str = field(default="", kw_only=True)


@dataclass(frozen=True)
class ColmapWritten(ExportWritten):
    """``colmap`` / ``limap``: where the ``model`` came from (the report's ``camera_model`` is
    then COLMAP's camera model), the image mirroring (``flip_u``) and rotation
    (``colmap_cam_from_cam``, 3 x 3) it needs, the model's images and points; ``colmap``: the
    ``images`` written; ``limap``: the counts of the LIMAP tracks (``tracks``, ``supported``,
    ``families``); ``rig``: a rig camera's lenses."""

    model: str = field(default="", kw_only=True)
    flip_u: bool = field(default=False, kw_only=True)
    colmap_cam_from_cam: list[list[float]] = field(default_factory=list, kw_only=True)
    num_images: int = field(default=0, kw_only=True)
    num_points3D: int = field(default=0, kw_only=True)
    images: str | None = field(default=None, metadata={_OMIT: True}, kw_only=True)
    limap: dict[str, int] | None = field(default=None, metadata={_OMIT: True}, kw_only=True)
    rig: dict[str, Any] | None = field(default=None, metadata={_OMIT: True}, kw_only=True)
    """A rig camera's COLMAP rig (``colmap`` of a rig camera): ``metres_per_unit`` (the scale
    of the sensors' translations) and ``lenses`` (each lens's images, COLMAP model,
    ``colmap_cam_from_cam``, ``flip_u`` and camera mask); ``flip_u`` and
    ``colmap_cam_from_cam`` above are then unset (false, empty)."""

    @property
    def images_written(self) -> int | None:
        return self.num_images


@dataclass(frozen=True)
class NerfstudioWritten(ExportWritten):
    """``nerfstudio``: what the ``images`` are, the perspective ``views`` (their layout, for
    cameras nerfstudio has no model of), the ``points`` file and ``num_images``."""

    images: str = field(default="", kw_only=True)
    views: dict[str, Any] | None = field(default=None, metadata={_OMIT: True}, kw_only=True)
    """:meth:`omni_sfm.export.perspective.ViewLayout.to_json` (a rig camera: ``{"lenses":
    [{"lens": k, ...}, ...]}``, each lens's)."""
    points: str | None = field(default=None, metadata={_OMIT: True}, kw_only=True)
    num_images: int = field(default=0, kw_only=True)

    @property
    def images_written(self) -> int | None:
        return self.num_images


@dataclass(frozen=True)
class RigWritten(ExportWritten):
    """``colmap-rig``: the images and frames (rig poses) of the model, the ``views`` layout,
    and where the ``images`` and ``masks`` are."""

    num_images: int = field(default=0, kw_only=True)
    num_frames: int = field(default=0, kw_only=True)
    views: dict[str, Any] = field(default_factory=dict, kw_only=True)
    """:meth:`omni_sfm.export.perspective.ViewLayout.to_json` (a rig camera: ``{"lenses":
    [{"lens": k, ...}, ...]}``, each lens's)."""
    images: str = field(default="", kw_only=True)
    masks: str = field(default="", kw_only=True)

    @property
    def images_written(self) -> int | None:
        return self.num_images


WRITTEN: dict[str, type[ExportWritten]] = {
    "tum": TrajectoryWritten, "kitti": TrajectoryWritten, "colmap": ColmapWritten,
    "limap": ColmapWritten, "nerfstudio": NerfstudioWritten, "colmap-rig": RigWritten}
"""The class of what each export format writes, by format."""


@dataclass(frozen=True)
class ExportReport(JsonReport):
    """An export's ``report.json`` (docs/formats.md, "Exports"): what every export records,
    then what its format's writer wrote (:data:`WRITTEN`, its keys at the top level), then
    ``seconds``."""

    omni_sfm_version: str
    format: str
    input: str
    """The exported folder (stored path)."""
    num_poses: int
    world: ExportWorld
    camera_model: str
    """The camera model (of the ``colmap`` and ``limap`` formats: COLMAP's, e.g. ``OPENCV``)."""
    written: ExportWritten = field(default_factory=ExportWritten)
    seconds: float = 0.0

    def to_json(self) -> dict[str, Any]:
        doc = super().to_json()
        seconds, written = doc.pop("seconds"), doc.pop("written")
        return {**doc, **written, "seconds": seconds}

    @classmethod
    def from_json(cls, doc: Any, where: str = "report") -> ExportReport:
        if not isinstance(doc, Mapping):
            raise OmniSfmError(f"{where}: not a JSON object")
        named = {f.name for f in fields(cls)}
        kind = WRITTEN.get(str(doc.get("format")), ExportWritten)
        written = kind.from_json({k: v for k, v in doc.items() if k not in named}, where)
        return super().from_json({**{k: v for k, v in doc.items() if k in named},
                                  "written": written}, where)

    @property
    def turned(self) -> bool:
        """The world was turned gravity-up."""
        return bool(self.world.turned)

    @property
    def num_images(self) -> int | None:
        """Images written, for formats that write images."""
        return self.written.images_written


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
    info: InitializerInfo | None = absent()

    _ORDER = ("status", "reason", "trajectory", "registered", "rot_max_deg", "rot_mean_deg",
              "ate_rel", "rpe", "rpe_rot_deg", "step_error_after_alignment",
              "frames_compared", "frames_registered", "time_s", "info")

    def to_json(self) -> dict[str, Any]:
        doc = super().to_json()
        return {**{k: doc[k] for k in self._ORDER if k in doc}, **self.other}


@dataclass(frozen=True)
class CompareSequence(JsonReport):
    """``results.json``'s ``sequence``: its name, number of frames and camera model."""

    name: str | None = absent()
    frames: int | None = absent()
    camera: str | None = absent()


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
