"""The model audit: localize the model's own photos and compare with their recorded poses.

A 3DGS model is fitted on photos whose poses come from a reconstruction (COLMAP, a phone's
tracking, LLFF). The audit localizes those photos (all, or ``sample`` evenly spread) with the
model, from ``starts`` perturbed starts around each recorded pose and from none, with the recorded
pose as ``gt_c2w`` (so the errors measure the agreement with the record, and the photo's own camera
is left out of its candidate views). Per camera it reports the agreement, the verdicts and the
signals, and flags the photos that disagree with their recorded pose (:func:`summarize_camera`):

- ``registration``: confident (``ok``) poses that agree with each other but not with the record:
  the source reconstruction registered this photo wrongly;
- ``no_trustworthy_pose``: no start gave an ``ok`` pose: a region the model renders badly (or a
  photo that does not show the scene);
- ``inconsistent``: ``ok`` poses that disagree with each other and with the record: a wrong
  ``ok``, or too few starts to say which.

    plan, rule = AuditPlan(starts=3), FlagRule()
    doc = run_audit(localizer, views, plan, rule, out_dir, scene_scale=..., scene_centre=...)
    doc["cameras"][0]["flag"], doc["cameras"][0]["reason"]

With ``control`` (the default) each photo also gets a control run: the model's own render at the
recorded pose, with the photo's camera, localized from the photo's first start (or none). It
measures what the method itself achieves on this model at that view. A photo whose pose lands
0.3 deg from its record while the model's render comes back to within 0.02 deg disagrees with
its record on this model (the record, or the model fitted on it, is off), not through the method.
Control runs are kept apart: they are not among the camera's verdicts and never flag it.

With ``focal_step`` (off by default) each photo is also localized from its recorded pose with its
recorded focal length scaled by ``1 - step``, ``1`` and ``1 + step`` (:func:`focal_agreement`):
where the photometric refinement's final loss is clearly lower at another focal length, the
photo's recorded intrinsics disagree with the model (a reconstruction that gave each photo its
own focal length can trade it against the camera's distance). Those runs are kept apart too.

``audit.json`` (rewritten atomically after each camera): ``settings``, ``rows`` (one per run: the
one row schema plus ``camera`` and ``start``), ``cameras`` (one summary per camera) and
``summary``. Every run is first appended to ``audit.jsonl``; a run on the same output folder
skips the runs it holds (resume; more ``starts`` or a larger ``sample`` add runs).
"""
from __future__ import annotations

import json
import logging
import os
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable, Dict, Iterable, List, Mapping, Optional, Sequence, Tuple

import numpy as np

from ..checks import check_bool, check_choice, check_int, check_pair, check_real
from ..io.atomic import write_json_atomic
from ..io.datasets.colmap_tracks import precision_of
from ..localization.types import VERDICTS, Query
from ..pose.convert import invert_rigid, rotation_error_deg, translation_error
from ..pose.precision import WITHIN_SIGMAS, rotation_sigmas
from .inputs import INIT_PIVOTS, natural_key, perturbed_start

logger = logging.getLogger(__name__)

__all__ = [
    "AUDIT_FORMAT",
    "CONTROL",
    "FLAGS",
    "AuditJournal",
    "AuditPlan",
    "FlagRule",
    "audit_pictures",
    "audit_starts",
    "audit_summary",
    "evenly_spread",
    "focal_agreement",
    "focal_label",
    "run_audit",
    "select_views",
    "summarize_camera",
]

AUDIT_FORMAT = "icomma-audit/1"
#: The flags of a camera (None: its photo agrees with its recorded pose).
FLAGS = ("registration", "no_trustworthy_pose", "inconsistent")


@dataclass
class AuditPlan:
    """Which photos are localized, and from which starts.

    starts: perturbed starts per photo. no_start: also localize each photo without a start.
    rot_deg: (lo, hi): each start is the recorded pose turned by an angle drawn in this range
        [deg] about ``pivot`` (``camera``, ``scene_center`` or ``origin``). trans: and moved by
        this distance [scene radii]. seed: the draws' seed (each photo's starts depend only on
        it and the photo's name). sample: localize this many photos, evenly spread over the
        name-sorted training photos (None: all). control: also localize the model's render at
        the recorded pose from the photo's first start (or none): the method's own precision
        on this model at that view (module docstring). focal_step: also localize each photo from
        its recorded pose with its focal length scaled by ``1 -+ focal_step`` and 1
        (:func:`focal_agreement`; None: not).
    """

    starts: int = 3
    no_start: bool = True
    rot_deg: Tuple[float, float] = (20.0, 40.0)
    trans: float = 0.05
    pivot: str = "camera"
    seed: int = 0
    sample: Optional[int] = None
    control: bool = True
    focal_step: Optional[float] = None

    def __post_init__(self):
        if isinstance(self.rot_deg, (int, float)) and not isinstance(self.rot_deg, bool):
            self.rot_deg = (float(self.rot_deg), float(self.rot_deg))
        self.rot_deg = check_pair(self.rot_deg, "rot_deg", 0.0, 180.0)
        check_int(self.starts, "starts", 0)
        check_bool(self.no_start, "no_start")
        check_real(self.trans, "trans", 0.0)
        check_choice(self.pivot, "pivot", INIT_PIVOTS)
        check_int(self.seed, "seed", 0)
        check_int(self.sample, "sample", 1, optional=True)
        check_bool(self.control, "control")
        check_real(self.focal_step, "focal.step", 0.0, 0.5, lo_open=True, optional=True)
        if self.starts == 0 and not self.no_start:
            raise ValueError("starts is 0 and no_start is false: each photo needs at least one "
                             "run (starts >= 1, or no_start=true)")

    def labels(self) -> List[str]:
        """The runs of each photo: ``none`` (no start) and ``start<k>`` (the control apart)."""
        return (["none"] if self.no_start else []) + [f"start{k}" for k in range(self.starts)]

    def runs_per_photo(self) -> int:
        """The photo's runs, its control run and its focal-length runs."""
        return len(self.labels()) + int(self.control) + len(self.focal_scales())

    def focal_scales(self) -> Tuple[float, ...]:
        """The focal-length scales of the focal check (none without ``focal_step``)."""
        if self.focal_step is None:
            return ()
        return (1.0 - self.focal_step, 1.0, 1.0 + self.focal_step)


#: The label of a photo's control run (:attr:`AuditPlan.control`).
CONTROL = "control"


@dataclass
class FlagRule:
    """When a camera is flagged (module docstring; docs/AUDIT.md).

    rot_deg, trans: two poses agree when they are less than this apart (degrees; scene radii);
        a pose agrees with the record likewise.
    min_ok: ``ok`` poses that must agree with each other before they contradict the record
        (fewer when a photo has fewer runs).
    focal_min_drop: the focal check (:func:`focal_agreement`) says a photo's recorded focal
        length disagrees with the model when another scale lowers the final loss by this share.
    """

    rot_deg: float = 5.0
    trans: float = 0.05
    min_ok: int = 2
    focal_min_drop: float = 0.05

    def __post_init__(self):
        check_real(self.rot_deg, "flag.rot_deg", 0.0, lo_open=True)
        check_real(self.trans, "flag.trans", 0.0, lo_open=True)
        check_int(self.min_ok, "flag.min_ok", 1)
        check_real(self.focal_min_drop, "focal.min_drop", 0.0, 1.0, lo_open=True)


# ---------------------------------------------------------------------------------- photos, starts


def evenly_spread(n: int, k: Optional[int]) -> List[int]:
    """``k`` indices of ``range(n)`` spread evenly, first and last included (all for None)."""
    if k is None or k >= n:
        return list(range(n))
    return sorted({int(round(x)) for x in np.linspace(0, n - 1, k)})


def select_views(views: Sequence[Any], sample: Optional[int]) -> List[Any]:
    """The photos to audit: ``views`` sorted by name (natural order), ``sample`` evenly spread."""
    ordered = sorted(views, key=lambda v: natural_key(str(v.name)))
    return [ordered[i] for i in evenly_spread(len(ordered), sample)]


def _seed_of(seed: int, name: str, k: int) -> int:
    """A start's seed from the plan's seed, the photo's name and the start's number."""
    ss = np.random.SeedSequence([seed, zlib.crc32(name.encode()), k])
    return int(ss.generate_state(1)[0])


def audit_starts(name: str, recorded_c2w: np.ndarray, plan: AuditPlan, scene_scale: float,
                 scene_centre: Optional[np.ndarray]) -> List[Tuple[str, Optional[np.ndarray]]]:
    """``(label, start c2w or None)`` of each run of photo ``name`` (:meth:`AuditPlan.labels`)."""
    out: List[Tuple[str, Optional[np.ndarray]]] = []
    for label in plan.labels():
        if label == "none":
            out.append((label, None))
            continue
        s = _seed_of(plan.seed, name, int(label[5:]))
        rng = np.random.default_rng(s)
        angle = float(rng.uniform(*plan.rot_deg))
        ini = {"rot_deg": angle, "trans": plan.trans * scene_scale, "pivot": plan.pivot,
               "seed": s}
        out.append((label, perturbed_start(recorded_c2w, ini, scene_centre)))
    return out


# ---------------------------------------------------------------------------------- the flag rule


def _apart(a: Mapping[str, Any], b: Mapping[str, Any], scale: float) -> Tuple[float, float]:
    """(rotation deg, centre distance in scene radii) between the poses of two rows."""
    ca, cb = np.asarray(a["c2w"], np.float64), np.asarray(b["c2w"], np.float64)
    return float(rotation_error_deg(ca, cb)), float(translation_error(ca, cb)) / scale


def _agrees_with_record(row: Mapping[str, Any], rule: FlagRule) -> bool:
    rot, trans = row.get("rot_err_deg"), row.get("trans_err_rel")
    return rot is not None and trans is not None and rot < rule.rot_deg and trans < rule.trans


def _consensus(ok: Sequence[Mapping[str, Any]], rule: FlagRule, scale: float
               ) -> Tuple[int, List[int]]:
    """(medoid, its group): the ``ok`` pose most others agree with, and those that do."""
    groups = []
    for i, a in enumerate(ok):
        near = [j for j, b in enumerate(ok)
                if j == i or all(x < t for x, t in zip(_apart(a, b, scale),
                                                       (rule.rot_deg, rule.trans)))]
        groups.append(near)
    best = max(range(len(ok)), key=lambda i: (len(groups[i]), -i))
    return best, groups[best]


def _scatter(ok: Sequence[Mapping[str, Any]], scale: float) -> Tuple[Optional[float],
                                                                        Optional[float]]:
    """(deg, radii): the largest rotation and centre distance between two ``ok`` poses."""
    if len(ok) < 2:
        return None, None
    pairs = [_apart(a, b, scale) for i, a in enumerate(ok) for b in ok[i + 1:]]
    return max(p[0] for p in pairs), max(p[1] for p in pairs)


def _median(values: Iterable[Optional[float]]) -> Optional[float]:
    v = [float(x) for x in values if x is not None]
    return float(np.median(v)) if v else None


def _untrusted_reason(rows: Sequence[Mapping[str, Any]]) -> str:
    """Why a camera without an ``ok`` pose is flagged: the counts, where its poses are, the doubt.

    The doubt is the reason of the run with the most agreeing matches.
    """
    counts = {v: sum(1 for r in rows if r.get("status") == v) for v in VERDICTS}
    rot = _median(r.get("rot_err_deg") for r in rows)
    trans = _median(r.get("trans_err_rel") for r in rows)
    best = max(rows, key=lambda r: r.get("inliers") or 0)
    where = "" if rot is None or trans is None else (
        f"; its poses are {rot:.2f} deg / {trans:.3f} radii from the record (median)")
    doubt = f"; best run: {best.get('reason')}" if best.get("reason") else ""
    return (f"no trustworthy pose from any of {len(rows)} starts ({counts['uncertain']} "
            f"uncertain, {counts['failed']} failed{where}{doubt}): a region the model renders "
            "badly, or a photo that does not show the scene")


def _flag(name: str, rows, ok, rule: FlagRule, scale: float) -> Dict[str, Any]:
    """The flag part of a camera's summary (see :func:`summarize_camera`)."""
    if not ok:
        return {"flag": "no_trustworthy_pose", "consensus": None,
                "reason": _untrusted_reason(rows)}
    medoid, group = _consensus(ok, rule, scale)
    need = min(rule.min_ok, len(rows))
    cons = ok[medoid]
    consensus = {"start": cons.get("start"), "size": len(group),
                 "rot_err_deg": cons.get("rot_err_deg"), "trans_err_rel": cons.get("trans_err_rel")}
    if len(group) >= need and 2 * len(group) > len(ok):
        if _agrees_with_record(cons, rule):
            return {"flag": None, "reason": None, "consensus": consensus}
        return {"flag": "registration", "consensus": consensus,
                "reason": f"photo {name} is at {cons['rot_err_deg']:.2f} deg / "
                          f"{cons['trans_err_rel']:.3f} radii from its recorded pose ({len(group)} "
                          f"of {len(rows)} starts agree on it, verdict ok): the source "
                          "reconstruction registered it wrongly"}
    if all(_agrees_with_record(r, rule) for r in ok):
        return {"flag": None, "reason": None, "consensus": None}
    rots = [r.get("rot_err_deg") for r in ok]
    return {"flag": "inconsistent", "consensus": None,
            "reason": f"{len(ok)} ok poses of {len(rows)} starts do not agree with each other "
                      f"nor all with the record (rotation off the record "
                      f"{min(rots):.2f}-{max(rots):.2f} deg): a wrong ok, or too few starts; "
                      "rerun with more starts"}


def summarize_camera(name: str, rows: Sequence[Mapping[str, Any]], rule: FlagRule,
                     scene_scale: float, control: Optional[Mapping[str, Any]] = None
                     ) -> Dict[str, Any]:
    """One camera's summary: agreement with the record, verdicts, signals and the flag.

    ``rows`` are its runs (the one row schema: ``status``, ``c2w``, ``rot_err_deg`` and
    ``trans_err_rel`` against the recorded pose). ``ok_scatter_deg`` / ``ok_scatter_radii``: the
    largest distance between two of its ``ok`` poses (how reproducible the localization is, to
    set beside its distance to the record). The flag rule (docs/AUDIT.md):

    1. no run ``ok``: ``no_trustworthy_pose``;
    2. else the consensus is the largest group of ``ok`` poses within ``rule.rot_deg`` /
       ``rule.trans`` of one of them (the medoid); it counts when it holds at least
       ``min(rule.min_ok, runs)`` poses and more than half the ``ok`` ones. A consensus off the
       record (the medoid's error not under both bounds) is ``registration``; on it, no flag;
    3. no consensus: no flag when every ``ok`` pose agrees with the record, else
       ``inconsistent``.

    ``control``: the camera's control run (:attr:`AuditPlan.control`), summarized apart
    (``control``: its errors against the record and its verdict; None without one).

    Raises:
        ValueError: no rows, or a scene scale that is not positive.
    """
    if not rows:
        raise ValueError(f"rows of camera {name!r} is empty: no run to summarize")
    check_real(scene_scale, "scene_scale", 0.0, lo_open=True)
    done = [r for r in rows if not r.get("error") and r.get("c2w") is not None]
    ok = [r for r in done if r.get("status") == "ok"]
    part = _flag(name, rows, ok, rule, scene_scale)
    scatter_deg, scatter_radii = _scatter(ok, scene_scale)
    cons = part["consensus"]
    shown = (next(r for r in ok if r.get("start") == cons["start"]) if cons else
             max(done, key=lambda r: r.get("inliers") or 0) if done else None)
    return {
        "camera": name,
        "runs": len(rows),
        "verdicts": {v: sum(1 for r in rows if r.get("status") == v) for v in VERDICTS},
        "errors": sum(1 for r in rows if r.get("error")),
        "ok_agreeing": sum(1 for r in ok if _agrees_with_record(r, rule)),
        "rot_err_deg": _median(r.get("rot_err_deg") for r in (ok or done)),
        "trans_err_rel": _median(r.get("trans_err_rel") for r in (ok or done)),
        "errors_of": "ok runs" if ok else "all runs",
        "ok_scatter_deg": scatter_deg,
        "ok_scatter_radii": scatter_radii,
        **part,
        "shown_start": None if shown is None else shown.get("start"),
        "status": None if shown is None else shown.get("status"),
        "c2w": None if shown is None else shown.get("c2w"),
        "recorded_c2w": rows[0].get("gt_c2w"),
        "signals": None if shown is None else shown.get("signals"),
        "control": None if control is None else {
            k: control.get(k) for k in ("start", "status", "rot_err_deg", "trans_err_rel",
                                        "error")},
    }


def attach_record(camera: Dict[str, Any], record: Optional[Mapping[str, Any]]) -> None:
    """Put a record's own precision on its camera summary (``record``, None without one).

    ``record_sigmas``: the Mahalanobis distance of the shown pose's rotation from the record's
    under the record's rotation covariance (``pose.precision.rotation_sigmas``); ``within_record``:
    at most ``WITHIN_SIGMAS`` (the photo and its record agree as far as the record can tell).
    """
    camera["record"] = None if record is None else dict(record)
    sig = None
    if record is not None and record.get("rot_cov") and camera.get("c2w") is not None \
            and camera.get("recorded_c2w") is not None:
        try:
            sig = rotation_sigmas(invert_rigid(np.asarray(camera["c2w"], np.float64)),
                                  invert_rigid(np.asarray(camera["recorded_c2w"], np.float64)),
                                  record["rot_cov"])
        except ValueError:  # a covariance that is not positive definite: nothing to say
            sig = None
    camera["record_sigmas"] = sig
    camera["within_record"] = None if sig is None else sig <= WITHIN_SIGMAS


def focal_label(scale: float) -> str:
    """The run label of the focal check at ``scale`` (``focal1.030``)."""
    return f"focal{scale:.3f}"


def focal_agreement(rows: Sequence[Mapping[str, Any]], scales: Sequence[float],
                    min_drop: float) -> Dict[str, Any]:
    """Whether a photo's recorded focal length is where the model explains it best.

    ``rows``: its runs from the recorded pose with the focal length scaled by ``scales`` (1 in the
    middle, one step either side). Each run ends at the photometric refinement's final loss
    (``details["refine_loss"][1]``: the exposure-fitted mean squared difference of render and
    photo at the model's side). ``best_scale``: the minimum of the parabola through the three
    losses (clamped to two steps either side; None where they are not convex); ``loss_drop``:
    the share of the loss at scale 1 that the better of the other two saves. ``disagrees``: that
    share is at least ``min_drop`` (None when a run has no loss: raised, or no refinement).
    """
    losses = []
    for r in rows:
        rl = (r.get("details") or {}).get("refine_loss")
        losses.append(float(rl[1]) if not r.get("error") and rl and rl[1] is not None else None)
    out = {"scales": [float(s) for s in scales], "losses": losses,
           "rot_err_deg": [r.get("rot_err_deg") for r in rows],
           "inliers": [r.get("inliers") for r in rows], "statuses": [r.get("status") for r in rows],
           "best_scale": None, "loss_drop": None, "disagrees": None}
    if len(losses) != 3 or any(v is None or not np.isfinite(v) for v in losses) or losses[1] <= 0:
        return out
    lo, mid, hi = losses
    step = (scales[2] - scales[0]) / 2.0
    curv = lo - 2.0 * mid + hi
    if curv > 0:
        off = float(np.clip(0.5 * (lo - hi) / curv, -2.0, 2.0))
        out["best_scale"] = float(scales[1] + off * step)
    out["loss_drop"] = float(max(0.0, (mid - min(lo, hi)) / mid))
    out["disagrees"] = bool(out["loss_drop"] >= min_drop)
    return out


def audit_summary(cameras: Sequence[Mapping[str, Any]], rows: Sequence[Mapping[str, Any]],
                  rule: FlagRule) -> Dict[str, Any]:
    """The audit's totals: runs, verdicts, flagged cameras by flag, ``ok`` poses off the record.

    ``ok_off_record_unflagged``: ``ok`` poses away from the record on unflagged cameras (the
    verdict's wrong ``ok`` if the records there are right).
    """
    from .lens import centre_reading

    flagged = {c["camera"] for c in cameras if c.get("flag")}
    ok = [r for r in rows if r.get("status") == "ok"]
    return {
        "cameras": len(cameras),
        "runs": len(rows),
        "verdicts": {v: sum(1 for r in rows if r.get("status") == v) for v in VERDICTS},
        "flagged": sorted(flagged, key=natural_key),
        "flags": {f: sum(1 for c in cameras if c.get("flag") == f) for f in FLAGS},
        "ok_agreeing": sum(1 for r in ok if _agrees_with_record(r, rule)),
        "ok_off_record_unflagged": sum(1 for r in ok if r.get("camera") not in flagged
                                       and not _agrees_with_record(r, rule)),
        "median_rot_err_deg_unflagged": _median(
            c.get("rot_err_deg") for c in cameras if not c.get("flag")),
        "median_ok_scatter_deg": _median(c.get("ok_scatter_deg") for c in cameras),
        # the method's own precision on this model: its renders at the records, localized back
        "median_control_rot_err_deg": _median(
            (c.get("control") or {}).get("rot_err_deg") for c in cameras),
        "median_control_trans_err_rel": _median(
            (c.get("control") or {}).get("trans_err_rel") for c in cameras),
        # how precisely the capture's own tracks fix its records (None without tracks)
        "median_record_rot_std_deg": _median(
            (c.get("record") or {}).get("rot_std_deg") for c in cameras),
        "record_points_free": any((c.get("record") or {}).get("points_free") for c in cameras),
        "unflagged_within_record": sum(1 for c in cameras
                                       if not c.get("flag") and c.get("within_record")),
        "unflagged_with_record": sum(1 for c in cameras
                                     if not c.get("flag") and c.get("within_record") is not None),
        # the focal check (None without it): photos whose recorded focal length the model doubts
        "focal_checked": sum(1 for c in cameras if (c.get("focal") or {}).get("disagrees")
                             is not None) if any(c.get("focal") for c in cameras) else None,
        "focal_disagreeing": sorted((c["camera"] for c in cameras
                                     if (c.get("focal") or {}).get("disagrees")),
                                    key=natural_key),
        # the lens the photos' refits agree on beyond their dataset's undistortion (the photo
        # runs, not the control's renders nor the focal check's scaled cameras)
        "lens": _lens_of(rows),
        # where the refits put the principal point of photos taken at the image centre (LLFF,
        # Blender, a model fitted with it), ``off`` when a batch's rule would adopt it; None when
        # the photos have one of their own (their refits do not free it)
        "principal_point": centre_reading(_photo_runs(rows)),
    }


def _lens_of(rows: Sequence[Mapping[str, Any]]) -> Optional[Dict[str, Any]]:
    """``lens.lens_evidence`` of the photo runs, and whether it says they are ``distorted``.

    ``distorted``: whether a batch's rule (``lens.LensConfig``'s defaults) would adopt it. None
    without refits.
    """
    from .lens import LensConfig, lens_evidence, photo_distortion

    photo_runs = _photo_runs(rows)
    ev = lens_evidence([photo_distortion(r) for r in photo_runs])
    if ev is not None:
        ev["distorted"] = LensConfig().adopt(photo_runs, None) is not None
    return ev


def _photo_runs(rows: Sequence[Mapping[str, Any]]) -> List[Dict[str, Any]]:
    """The runs of the photos themselves: not the control's renders nor the focal check's."""
    return [dict(r) for r in rows if r.get("start") != CONTROL
            and not str(r.get("start")).startswith("focal")]


# ---------------------------------------------------------------------------------- resume


class AuditJournal:
    """``audit.jsonl``: every run as one JSON line, so a killed audit resumes where it stopped.

    The first line holds the audit's identity (model, dataset, the starts' draws, method,
    matcher); a folder holding another audit's journal is refused (ValueError naming it).
    """

    def __init__(self, out_dir: Path, identity: Mapping[str, Any]):
        self.path = Path(out_dir) / "audit.jsonl"
        self.identity = json.loads(json.dumps(identity, default=str))
        self.rows: Dict[Tuple[str, str], Dict[str, Any]] = {}
        if self.path.is_file():
            self._load()

    def _load(self) -> None:
        for n, line in enumerate(self.path.read_text().splitlines()):
            try:
                obj = json.loads(line)
            except json.JSONDecodeError:
                logger.warning("%s: line %d cut short (a kill while writing); ignored",
                               self.path, n + 1)
                continue
            if n == 0 and "audit" in obj:
                if obj["audit"] != self.identity:
                    diff = sorted(k for k in set(obj["audit"]) | set(self.identity)
                                  if obj["audit"].get(k) != self.identity.get(k))
                    raise ValueError(
                        f"output.dir: {self.path} belongs to another audit (it differs in "
                        f"{', '.join(diff)}); choose another output.dir to start a new one")
            elif isinstance(obj, dict) and "camera" in obj and "start" in obj:
                self.rows[(obj["camera"], obj["start"])] = obj

    def has(self, camera: str, start: str) -> bool:
        """Whether the run ``(camera, start)`` is recorded."""
        return (camera, start) in self.rows

    def record(self, row: Dict[str, Any]) -> None:
        """Append a run (flushed to disk at once)."""
        new = not self.path.is_file()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.path, "a") as fh:
            if new:
                fh.write(json.dumps({"audit": self.identity}) + "\n")
            fh.write(json.dumps(row) + "\n")
            fh.flush()
            os.fsync(fh.fileno())
        self.rows[(row["camera"], row["start"])] = row


# ---------------------------------------------------------------------------------- the run


def _localize(localizer, query: Query, camera: str, label: str, init, recorded, scale: float
              ) -> Dict[str, Any]:
    """One run as a row (the one row schema plus ``camera`` and ``start``)."""
    from ..localization.types import blank_row

    try:
        res = localizer.localize(query, init_c2w=init, gt_c2w=recorded)
    except (ValueError, RuntimeError) as e:  # one run's failure never stops the audit
        logger.warning("audit of %s (%s) raised %s: %s", camera, label, type(e).__name__, e)
        return blank_row(name=camera, status="failed", reason="the localization raised",
                         error=f"{type(e).__name__}: {e}", camera=camera, start=label,
                         gt_c2w=np.asarray(recorded).tolist(), scene_scale=scale)
    return res.row(scale, camera=camera, start=label)


def _control_query(localizer, view, recorded: np.ndarray, scale: float) -> Query:
    """The model's render at the recorded pose, with the photo's camera at ``scale``."""
    import torch

    from ..pose.convert import invert_rigid
    from ..render import render

    intr = view.intrinsics if scale == 1.0 else view.intrinsics.scaled(scale)
    model = localizer.model
    w2c = torch.as_tensor(invert_rigid(recorded), dtype=model.dtype, device=model.device)
    with torch.no_grad():
        out = render(model, intr, w2c, localizer.background, backend=localizer.backend)
    return Query(out.color.clamp(0.0, 1.0).float().cpu(), intr,
                 name=f"{view.name} (the model's render at its record)")


def _focal_query(query: Query, scale: float) -> Query:
    """``query`` with its focal lengths scaled by ``scale`` (the same pixels)."""
    return Query(query.rgb, query.intrinsics.with_focal_scale(scale), query.alpha, query.valid,
                 query.name)


def _document(settings, rows, controls, cameras, rule, status: str,
              focals=()) -> Dict[str, Any]:
    return {"format": AUDIT_FORMAT, "status": status, "settings": settings,
            "summary": audit_summary(cameras, rows, rule), "cameras": cameras, "rows": rows,
            "controls": controls, "focal_runs": list(focals),
            "conventions": "c2w: 4x4 camera-to-world, OpenCV axes; *_rel and trans in scene "
                           "radii (scene_scale); errors are against the recorded pose"}


def run_audit(localizer, views: Sequence[Any], plan: AuditPlan, rule: FlagRule, out_dir,
              *, scene_scale: float, scene_centre: Optional[np.ndarray] = None,
              image_scale: Callable[[Any], float] = lambda v: 1.0,
              settings: Optional[Dict[str, Any]] = None,
              identity: Optional[Dict[str, Any]] = None,
              on_camera: Optional[Callable[[Any, Query, Dict[str, Any]], Any]] = None,
              progress: bool = True,
              records: Optional[Mapping[str, Mapping[str, Any]]] = None) -> Dict[str, Any]:
    """Audit ``views`` (already selected) with ``localizer``; write and return ``audit.json``.

    Args:
        localizer: a ``Localizer`` of the model (its cameras' recorded poses are the records).
        views: the photos (``io.datasets.View``s: name, recorded ``c2w``, ``load_image``).
        plan: the runs of each photo.
        rule: the flag rule.
        out_dir: the output folder (audit.json, audit.jsonl).
        scene_scale: the scene radius (the unit of ``trans`` and of ``*_rel``).
        scene_centre: the ``scene_center`` pivot.
        image_scale: a view's load scale (the model's training scale).
        settings: stored in audit.json (the run's config).
        identity: what must not change between a run and the one it resumes
            (:class:`AuditJournal`).
        on_camera: called with (view, query, camera summary) after each camera (thumbnails).
        progress: a tqdm bar over the runs.
        records: each record's own precision by photo name (``colmap_tracks.record_precision``;
            None or {} when the capture has no tracks): attached to its camera (``record``).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    settings = dict(settings or {}, plan=asdict(plan), flag=asdict(rule), scene_scale=scene_scale)
    journal = AuditJournal(out, {**(identity or {}), "rot_deg": list(plan.rot_deg),
                                 "trans": plan.trans, "pivot": plan.pivot, "seed": plan.seed})
    bar = _Progress(progress, len(views) * plan.runs_per_photo())
    rows: List[Dict[str, Any]] = []
    controls: List[Dict[str, Any]] = []
    focals: List[Dict[str, Any]] = []
    cameras: List[Dict[str, Any]] = []
    bg = localizer.background.detach().float().cpu()
    try:
        for view in views:
            name = str(view.name)
            recorded = np.asarray(view.c2w, np.float64)
            query = None
            cam_rows = []
            starts = audit_starts(name, recorded, plan, scene_scale, scene_centre)
            for label, init in starts:
                if not journal.has(name, label):
                    query = query or Query.from_view(view, bg, image_scale(view))
                    journal.record(_localize(localizer, query, name, label, init, recorded,
                                             scene_scale))
                cam_rows.append(journal.rows[(name, label)])
                bar.run(cam_rows[-1], cameras)
            control = None
            if plan.control:
                if not journal.has(name, CONTROL):  # from the first start (or none)
                    init = next((c2w for _, c2w in starts if c2w is not None), None)
                    journal.record(_localize(
                        localizer, _control_query(localizer, view, recorded, image_scale(view)),
                        name, CONTROL, init, recorded, scene_scale))
                control = journal.rows[(name, CONTROL)]
                controls.append(control)
                bar.run(None, cameras)
            focal_rows = []
            for f in plan.focal_scales():
                label = focal_label(f)
                if not journal.has(name, label):
                    query = query or Query.from_view(view, bg, image_scale(view))
                    journal.record(_localize(localizer, _focal_query(query, f), name, label,
                                             recorded, recorded, scene_scale))
                focal_rows.append(journal.rows[(name, label)])
                bar.run(None, cameras)
            focals += focal_rows
            rows += cam_rows
            cameras.append(summarize_camera(name, cam_rows, rule, scene_scale, control))
            attach_record(cameras[-1], precision_of(records or {}, name))
            cameras[-1]["focal"] = (focal_agreement(focal_rows, plan.focal_scales(),
                                                    rule.focal_min_drop) if focal_rows else None)
            if on_camera is not None:
                on_camera(view, query or Query.from_view(view, bg, image_scale(view)),
                          cameras[-1])
            write_json_atomic(out / "audit.json", _document(settings, rows, controls, cameras,
                                                            rule, "running", focals))
    finally:
        bar.close()
    doc = _document(settings, rows, controls, cameras, rule, "complete", focals)
    write_json_atomic(out / "audit.json", doc)
    return doc


class _Progress:
    """A tqdm bar over the runs, its postfix the verdict counts and the flagged cameras."""

    def __init__(self, enabled: bool, total: int):
        self.counts = {v: 0 for v in VERDICTS}
        self.bar = None
        if enabled:
            from tqdm import tqdm

            self.bar = tqdm(total=total, desc="audit", unit="run", dynamic_ncols=True)

    def run(self, row: Optional[Mapping[str, Any]], cameras: Sequence[Mapping[str, Any]]
            ) -> None:
        """Count one run (done now or read from the journal; None: a control run, not counted)."""
        if row is not None and row.get("status") in self.counts:
            self.counts[row["status"]] += 1
        if self.bar is not None:
            flagged = sum(1 for c in cameras if c.get("flag"))
            self.bar.set_postfix({**self.counts, "flagged": flagged}, refresh=False)
            self.bar.update(1)

    def close(self) -> None:
        """Close the bar."""
        if self.bar is not None:
            self.bar.close()


# ---------------------------------------------------------------------------------- pictures


def audit_pictures(out_dir, doc: Mapping[str, Any], cameras_c2w: Optional[Sequence] = None,
                   title: str = "", sheet: bool = True, trajectory: bool = True
                   ) -> Dict[str, str]:
    """The contact sheet and the trajectory plot of an audit (flagged cameras marked).

    The sheet's thumbnails are ``thumbs/<camera>.png`` when present (written by the tool: each
    photo blended with the render at its recorded pose). The plot shows ``cameras_c2w`` (all the
    model's cameras; default: the audited ones) in grey, the audited cameras' recorded centres
    (dashed) and localized ones (verdict colours), the flagged ringed and joined to their record.
    ``sheet`` / ``trajectory``: draw that picture. Returns ``{picture: file name}``; a picture
    that cannot be drawn is logged, never fatal.
    """
    from ..pictures import contact_sheet, plot_trajectory
    from .batch.records import safe_name

    out = Path(out_dir)
    cams = list(doc.get("cameras") or [])
    files: Dict[str, str] = {}
    if not cams:
        return files
    flags = {c["camera"]: c["flag"] for c in cams if c.get("flag")}
    sheet_rows = [{"name": c["camera"], "status": c.get("status"),
                   "rot_err_deg": c.get("rot_err_deg"), "trans_err_rel": c.get("trans_err_rel"),
                   "thumb": f"thumbs/{safe_name(c['camera'])}.png"} for c in cams]
    try:
        if sheet:
            contact_sheet(out / "contact_sheet.png", sheet_rows, out, flags=flags)
            files["contact_sheet"] = "contact_sheet.png"
    except Exception as e:  # noqa: BLE001 - a picture never fails the audit
        logger.warning("no contact sheet: %s: %s", type(e).__name__, e)
    if not trajectory:
        return files
    try:
        plot_trajectory(
            out / "trajectory.png",
            [None if c.get("c2w") is None else np.asarray(c["c2w"]) for c in cams],
            [np.asarray(c["recorded_c2w"]) for c in cams] if cameras_c2w is None
            else [np.asarray(c) for c in cameras_c2w],
            gt_c2w=[np.asarray(c["recorded_c2w"]) for c in cams],
            statuses=[c.get("status") or "failed" for c in cams],
            title=title or f"audit: {len(flags)} of {len(cams)} cameras flagged",
            flagged=[bool(c.get("flag")) for c in cams],
            labels={"estimated": "localized", "truth": "recorded", "cameras": "recorded cameras"},
        )
        files["trajectory"] = "trajectory.png"
    except Exception as e:  # noqa: BLE001 - a picture never fails the audit
        logger.warning("no trajectory plot: %s: %s", type(e).__name__, e)
    return files
