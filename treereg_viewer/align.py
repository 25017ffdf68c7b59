"""The "Align" tab: a failed or unverified scan aligned by hand (issue 33), then refined by the pipeline.

The user picks the same point on the reference and on the scan, three times or more (a click in 3-D
on either tree: the reference stands where it is, the scan beside it), the pairs are listed, each
removable, with the fit's residual (the core's `geometry.point_pairs`: Kabsch on the pairs); *Refine
from here* gives the fit to the pipeline as the scan's start pose (`Controller.start` ->
`Pipeline.start`, on the worker): the stages from the coarse stage on run from it, and the verdict
judges it as any pose. The app computes no geometry here: the fit and its frames are the core's.

While a tab aligns, its drawer hides the scan and stage layers (`ViewState.align_scan`); this panel
draws the two trees and the picks under `/align`.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np
import viser
import viser.transforms as vtf

from treereg_core.coarse.start import StartPose
from treereg_core.errors import ConfigError
from treereg_core.io.json_input import parse_json
from treereg_core.io.start import MAX_START_BYTES, read_start, saved_starts
from treereg_core.text import shown as shown_text
from treereg_core.geometry.picking import nearest_to_ray
from treereg_core.geometry.point_pairs import MIN_PAIRS, PairFit, as_file_frames, fit_point_pairs
from treereg_core.prepare.ground import PreparedScan

from .camera import CameraPose
from .controller import Controller, Snapshot
from .draw.common import display_subset, pose_kwargs
from .labels import verdict_badge
from .palette import scan_color
from .export import STARTS_NAME, starts_file
from .text import md
from .uploads import UploadReceiver, discard

log = logging.getLogger(__name__)

#: Points of each tree drawn (and clicked on) while aligning.
ALIGN_POINTS = 20_000
#: How close to a click's ray a point must be to count (deg).
PICK_ANGLE_DEG = 0.8
#: Room between the reference's tree and the scan's drawn beside it (m).
GAP_M = 2.0
#: Where the start came from, as transforms.json's quality ("started_from") and the messages say it.
SOURCE = "the app"
NONE = "(none)"
#: The picked points: small spheres, and each pair's line, in a colour no scan has.
MARK_RADIUS_M = 0.05
MARK_COLOUR = (255, 200, 0)

Xyz = tuple[float, float, float]


def saved_start_poses(path: Path, filename: str, doc: Any, names: list[str],
                      source: str | None = None) -> tuple[list[tuple[str, StartPose]], list[str]]:
    """The start poses a received JSON file holds for the loaded target scans `names[1:]` (a starts.json
    or transforms.json, or the "starts" a params.json carries, `io.start.saved_starts`), each read as
    `register --initial` reads it, and the names it gives starts for that are not loaded. Each pose's
    source: `source` when given, else the one the file recorded for it (a params.json's "sources"),
    else `filename`.
    ([], []) for a doc that lists none (a plain matrix); ConfigError for a bad entry."""
    doc = saved_starts(doc)
    if not isinstance(doc, dict) or not isinstance(doc.get("transforms"), dict):
        return [], []
    unverified = doc.get("unverified")
    listed = list(doc["transforms"]) + (list(unverified) if isinstance(unverified, dict) else [])
    recorded = doc.get("sources")
    sources: dict[str, Any] = recorded if isinstance(recorded, dict) else {}
    poses = []
    for n in [n for n in names[1:] if n in listed]:
        saved = sources.get(n)
        given = source or (saved if isinstance(saved, str) and saved else filename)
        poses.append((n, replace(read_start(path, n), source=shown_text(given))))
    return poses, [n for n in listed if n not in names and n != doc.get("reference")]


@dataclass(frozen=True, kw_only=True)
class PickedPair:
    """One pair: the same point on the reference and on the scan, each in its scan's frame as the
    stages see it (scanner frame, levelled)."""

    ref_xyz: Xyz
    tgt_xyz: Xyz


@dataclass(frozen=True, kw_only=True)
class AlignState:
    """What one tab is aligning: the scan, the pairs so far and the half-picked pair."""

    scan: str | None = None
    pairs: tuple[PickedPair, ...] = ()
    ref_pick: Xyz | None = None
    tgt_pick: Xyz | None = None
    preview: bool = False
    moved: tuple[tuple[float, ...], ...] | None = None  # the scan moved with the gizmo: its 4x4 T_ref_tgt

    def moved_pose(self) -> np.ndarray | None:
        return None if self.moved is None else np.array(self.moved, dtype=float)

    def fit(self) -> PairFit:
        ref = np.array([p.ref_xyz for p in self.pairs], dtype=float).reshape(-1, 3)
        tgt = np.array([p.tgt_xyz for p in self.pairs], dtype=float).reshape(-1, 3)
        return fit_point_pairs(ref, tgt)


def candidates(snap: Snapshot) -> list[str]:
    """The scans a person may align by hand: those the Placement stage failed or left unverified, and
    those started by hand already (to adjust the start)."""
    names = [s.name for s in snap.scans[1:]]
    return [n for n in names if snap.verdicts.get(n, ("",))[0] in ("failed", "unverified") or n in snap.starts]


def _xyz(p: np.ndarray) -> Xyz:
    return (float(p[0]), float(p[1]), float(p[2]))


class AlignPanel:
    """The Align tab of one viewer.

    Parameters
    ----------
    gui, scene
        The viewer's.
    controller
        Where the start goes.
    set_align
        Tells the viewer which scan this tab aligns (None: none), so its drawer hides its layers.
    look
        Points the tab's camera.
    refined
        Called once a start is given (the viewer shows the Placement stage, where the verdict comes).
    uploads, send_file
        The app's upload receiver and browser downloads (the start poses as a file, and back).
    """

    def __init__(self, gui: viser.GuiApi, scene: viser.SceneApi, controller: Controller,
                 set_align: Callable[[str | None], None], look: Callable[[CameraPose], None],
                 refined: Callable[[], None] = lambda: None, uploads: UploadReceiver | None = None,
                 send_file: Callable[[Any, str, bytes], None] | None = None) -> None:
        self.gui = gui
        self.scene = scene
        self.controller = controller
        self._set_align = set_align
        self._look = look
        self._refined = refined
        self._lock = threading.RLock()
        self.state = AlignState()
        self._nodes: dict[str, Any] = {}
        self._clouds_key: tuple[Any, ...] | None = None
        self._ref_pts = np.zeros((0, 3))
        self._tgt_pts = np.zeros((0, 3))
        self._D = np.eye(4)  # where the scan is drawn: its displayed point = D @ its point
        gui.add_markdown(
            "**Align by hand** a scan that *11 Placement* failed (✗) or left unverified (⚠): click the same "
            "point on the reference (left) and on the scan (right), three times or more, spread over the tree "
            "(the stem low and high, a branch to each side). *Refine from here* then runs the stages from "
            "*4 Coarse* on from your alignment; the verdict judges it as any pose (a wrong one is refused).")
        self.scan_choice = gui.add_dropdown("Scan", (NONE,), hint="A scan whose verdict is ✗ failed or ⚠ unverified.")
        #: Set while the tab follows the presenter: no start pose given, nothing run from here.
        self.locked = False
        self.start_button = gui.add_button("Align this scan by hand", icon=viser.Icon.HAND_CLICK, disabled=True)
        self.stop_button = gui.add_button("Stop aligning", icon=viser.Icon.X, color="gray", visible=False)
        self.status_md = gui.add_markdown("")
        self.pairs_md = gui.add_markdown("")
        self.pair_choice = gui.add_dropdown("Pair", (NONE,), visible=False)
        self.remove_button = gui.add_button("Remove pair", icon=viser.Icon.TRASH, color="gray", visible=False)
        self.clear_button = gui.add_button("Clear all pairs", icon=viser.Icon.TRASH, color="gray", visible=False)
        self.preview_box = gui.add_checkbox("Show the scan at the fit", False, visible=False,
                                            hint="Draws the scan where the picked pairs put it, over the reference.")
        self.gizmo_box = gui.add_checkbox("Move the scan with the gizmo", False, visible=False,
                                          hint="Drag the arrows and rings to put the scan over the reference; "
                                               "Refine from here then starts from where you put it.")
        self.refine_button = gui.add_button("Refine from here", icon=viser.Icon.PLAYER_PLAY, color="blue",
                                            visible=False, disabled=True)
        self.forget_button = gui.add_button("Forget the start pose", icon=viser.Icon.X, color="gray", visible=False,
                                            hint="The coarse stage estimates this scan's pose again.")
        self.verdict_md = gui.add_markdown("")
        self.download_starts = gui.add_button(f"Download start poses ({STARTS_NAME})", icon=viser.Icon.DOWNLOAD,
                                              visible=False, hint="The start poses given by hand, as a file "
                                              "treereg register --initial SCAN=starts.json reads (the exports hold it too).")
        self.load_starts = gui.add_upload_button("Load start poses (JSON or 4x4 text)", icon=viser.Icon.UPLOAD,
                                                 mime_type="*/*", hint="A starts.json or transforms.json (its entries "
                                                 "for the loaded scans), or 4 rows of 4 numbers for the scan chosen above.")
        self._send_file = send_file
        self.download_starts.on_click(lambda e: self._download_starts(e.client))
        if uploads is not None:
            uploads.add(self.load_starts, self.load_start_file, MAX_START_BYTES, what="start pose file")
        else:
            self.load_starts.visible = False
        self.start_button.on_click(lambda _: self.begin(str(self.scan_choice.value)))
        self.stop_button.on_click(lambda _: self.end())
        self.remove_button.on_click(lambda _: self.remove(self._pair_index()))
        self.clear_button.on_click(lambda _: self.clear())
        self.preview_box.on_update(lambda _: self.set_preview(bool(self.preview_box.value)))
        self.gizmo_box.on_update(lambda _: self.set_gizmo(bool(self.gizmo_box.value)))
        self._gizmo: Any = None
        self.refine_button.on_click(lambda _: self.refine())
        self.forget_button.on_click(lambda _: self.forget())
        self.scan_choice.on_update(lambda _: self._show_verdict(self.controller.snapshot))
        self._names: tuple[str, ...] = ()

    # ---- the snapshot --------------------------------------------------------------------------
    def show_snapshot(self, snap: Snapshot) -> None:
        """The scans a person may align, and the chosen scan's verdict (after a refine: the new one)."""
        names = tuple(candidates(snap))
        with self._lock:
            if names != self._names:
                self._names = names
                current = self.scan_choice.value
                self.scan_choice.options = names or (NONE,)
                if current in names:
                    self.scan_choice.value = current  # type: ignore[misc]
            self.start_button.disabled = not names or self.state.scan is not None
            if self.state.scan is not None and self.state.scan not in [s.name for s in snap.scans]:
                self.end()  # the scan was removed
        self.download_starts.visible = bool(snap.starts) and self._send_file is not None
        self._show_verdict(snap)

    def _download_starts(self, client: Any) -> None:
        snap = self.controller.snapshot
        if snap.starts and self._send_file is not None:
            self._send_file(client, STARTS_NAME, starts_file(snap))

    def load_start_file(self, filename: str, path: Path) -> None:
        """A start pose file received from the browser (`io.start`, as `register --initial` reads it):
        a transforms.json's entries for every loaded target scan it names, or a matrix for the scan
        chosen above; each given to the pipeline, which runs from there. A bad file: one message."""
        if self.locked:  # the tab follows the presenter: start poses and runs are the presenter's
            discard(path)
            return
        snap = self.controller.snapshot
        names = [s.name for s in snap.scans]
        name = Path(filename).name or "upload"
        try:
            data = path.read_bytes()
            text = data.decode("utf-8-sig", errors="replace")
            doc = parse_json(data, name) if text.lstrip().startswith(("{", "[")) else None
            if isinstance(saved_starts(doc), dict) and isinstance(saved_starts(doc).get("transforms"), dict):
                poses, _ = saved_start_poses(path, name, doc, names, source=name)
                if not poses:
                    raise ConfigError(f"{name}: names none of the loaded target scans ({', '.join(names[1:])})")
            else:
                chosen = str(self.scan_choice.value)
                if chosen not in names[1:]:
                    raise ConfigError(f"{name}: a matrix is the start of the scan chosen above: choose one first")
                poses = [(chosen, replace(read_start(path, chosen), source=shown_text(name)))]
        except (ConfigError, OSError) as e:
            self.controller.note(f"Start poses not loaded — {str(e).replace(str(path), name)}", error=True)
            return
        finally:
            discard(path)
        for n, pose in poses:
            self.controller.start(n, pose)
        self._refined()

    def _show_verdict(self, snap: Snapshot) -> None:
        name = self.state.scan or str(self.scan_choice.value)
        if name not in [s.name for s in snap.scans[1:]]:
            self.verdict_md.content = ("" if snap.verdicts else
                                       "*Run the pipeline to its verdicts first: a scan to align is one it failed "
                                       "or left unverified.*")
            self.forget_button.visible = False
            return
        verdict, reasons, _ = snap.verdicts.get(name, ("", (), ""))
        start = snap.starts.get(name)
        lines = []
        if snap.busy:
            lines.append(f"*Running… ({md(name)})*")
        elif verdict:
            lines.append(f"**{md(name)}: {verdict_badge(verdict)}**")
            lines += [f"- {md(r)}" for r in reasons[:3]]
        if start is not None:
            lines.append(f"Started from the pose given in {md(start.source)}.")
        i = [s.name for s in snap.scans].index(name)
        if snap.pairs and snap.reference_pair(i) is None:
            # The pipeline takes a start for a scan's pair with the reference (or a pair of two started scans).
            lines.append(f"⚠ {md(name)} is not paired with the reference in this run, so a start pose given "
                         "here takes effect only for its pairs with other scans given starts too.")
        self.verdict_md.content = "\n\n".join(lines)
        self.forget_button.visible = start is not None

    # ---- aligning --------------------------------------------------------------------------------
    def begin(self, name: str) -> None:
        """Start aligning scan `name`: both trees drawn side by side, the tab's layers hidden."""
        snap = self.controller.snapshot
        names = [s.name for s in snap.scans]
        if name not in names[1:]:
            return
        i = names.index(name)
        ref, tgt = snap.scan_item("prepare", 0, PreparedScan), snap.scan_item("prepare", i, PreparedScan)
        if ref is None or tgt is None:
            self.status_md.content = "The scans are not prepared yet: run the pipeline first."
            return
        with self._lock:
            self.state = AlignState(scan=name)
            r, t = ref.scan.points, tgt.scan.points
            self._ref_pts = r[display_subset(len(r), ALIGN_POINTS, seed=5)]
            self._tgt_pts = t[display_subset(len(t), ALIGN_POINTS, seed=6)]
            self._D = self._beside()
            self._clouds_key = None
            self._set_align(name)
            self._draw()
            self._show_controls(True)
        lo, hi = self._bounds()
        centre = (lo + hi) / 2
        size = float(np.max(hi - lo))
        self._look(CameraPose(position=_xyz(centre + np.array([0.0, -1.1 * size, 0.35 * size])), look_at=_xyz(centre)))

    def end(self) -> None:
        """Stop aligning: the picks are dropped, the tab's layers come back."""
        with self._lock:
            self.state = AlignState()
            for h in self._nodes.values():
                try:
                    h.remove()
                except Exception:  # gone with its tab
                    pass
            self._nodes = {}
            if self._gizmo is not None:
                self._gizmo.remove()
                self._gizmo = None
            self._clouds_key = None
            self._set_align(None)
            self._show_controls(False)
        self._show_verdict(self.controller.snapshot)

    def _beside(self) -> np.ndarray:
        """Where the scan is drawn while pairs are picked: beside the reference's tree (to its right
        as the camera looks), their lowest points level, so a click is on one tree or the other."""
        r, t = self._ref_pts, self._tgt_pts
        shift = np.array([r[:, 0].max() + GAP_M - t[:, 0].min(),
                          float(np.median(r[:, 1]) - np.median(t[:, 1])),
                          r[:, 2].min() - t[:, 2].min()])
        D = np.eye(4)
        D[:3, 3] = shift
        return D

    def _bounds(self) -> tuple[np.ndarray, np.ndarray]:
        t = self._tgt_pts @ self._D[:3, :3].T + self._D[:3, 3]
        both = np.vstack([self._ref_pts, t])
        return both.min(axis=0), both.max(axis=0)

    def pick(self, origin: np.ndarray, direction: np.ndarray) -> bool:
        """A click in 3-D while aligning: the point it meant on either tree (the nearer to the camera
        when both are near the ray) completes a pair with the other tree's last pick. False when this
        tab is not aligning (the viewer handles the click)."""
        with self._lock:
            if self.state.scan is None:
                return False
            shown_tgt = self._tgt_pts @ self._D[:3, :3].T + self._D[:3, 3]
            hits = []
            for side, pts in (("ref", self._ref_pts), ("tgt", shown_tgt)):
                k = nearest_to_ray(pts, origin, direction, max_angle_deg=PICK_ANGLE_DEG)
                if k is not None:
                    hits.append((float((pts[k] - origin) @ direction), side, k))
            if not hits:
                return True
            _, side, k = min(hits)
            if side == "ref":
                self.add_pick(ref=_xyz(self._ref_pts[k]))
            else:
                self.add_pick(tgt=_xyz(self._tgt_pts[k]))
            return True

    def add_pick(self, ref: Xyz | None = None, tgt: Xyz | None = None) -> None:
        """A point picked on the reference (`ref`) or the scan (`tgt`), in its scan's frame; a pair is
        complete when both sides have one."""
        with self._lock:
            s = self.state
            s = replace(s, ref_pick=ref if ref is not None else s.ref_pick, tgt_pick=tgt if tgt is not None else s.tgt_pick)
            if s.ref_pick is not None and s.tgt_pick is not None:
                s = replace(s, pairs=(*s.pairs, PickedPair(ref_xyz=s.ref_pick, tgt_xyz=s.tgt_pick)),
                            ref_pick=None, tgt_pick=None)
            self.state = s
            self._changed()

    def remove(self, k: int | None) -> None:
        with self._lock:
            if k is None or not 0 <= k < len(self.state.pairs):
                return
            pairs = self.state.pairs
            self.state = replace(self.state, pairs=pairs[:k] + pairs[k + 1:])
            self._changed()

    def clear(self) -> None:
        with self._lock:
            self.state = replace(self.state, pairs=(), ref_pick=None, tgt_pick=None)
            self._changed()

    def set_preview(self, on: bool) -> None:
        with self._lock:
            if self.state.scan is None or on == self.state.preview:
                return
            self.state = replace(self.state, preview=on)
            self._changed()

    def _pair_index(self) -> int | None:
        v = str(self.pair_choice.value)
        return int(v.split()[1]) - 1 if v.startswith("Pair ") else None

    def _changed(self) -> None:
        fit = self.state.fit()
        if not fit.ok and self.state.preview:
            self.state = replace(self.state, preview=False)
        moved = self.state.moved_pose()
        self._D = moved if moved is not None else fit.T_ref_tgt if self.state.preview and fit.ok else self._beside()
        self._draw()
        self._show_pairs(fit)

    # ---- the gizmo ---------------------------------------------------------------------------------
    def _centre(self) -> np.ndarray:
        """The scan's tree's centre (its frame): where the gizmo turns it about."""
        out: np.ndarray = np.median(self._tgt_pts, axis=0)
        return out

    def set_gizmo(self, on: bool) -> None:
        """Move the scan with viser's transform controls (on), from where it is drawn now; off: the
        pairs' fit (or beside the reference) again."""
        with self._lock:
            if self.state.scan is None or on == (self.state.moved is not None):
                return
            if not on:
                self.state = replace(self.state, moved=None)
                if self._gizmo is not None:
                    self._gizmo.remove()
                    self._gizmo = None
                self._changed()
                return
            C = np.eye(4)
            C[:3, 3] = self._centre()
            G = self._D @ C
            kw = pose_kwargs(G)
            self._gizmo = self.scene.add_transform_controls("/align/gizmo", scale=3.0, depth_test=False,
                                                            wxyz=kw["wxyz"], position=kw["position"])
            self._gizmo.on_update(lambda _: self._dragged())
            self.move_to(G)

    def _dragged(self) -> None:
        g = self._gizmo
        if g is None:
            return
        G = np.eye(4)
        G[:3, :3] = vtf.SO3(np.asarray(g.wxyz, dtype=float)).as_matrix()
        G[:3, 3] = np.asarray(g.position, dtype=float)
        self.move_to(G)

    def move_to(self, G: np.ndarray) -> None:
        """The gizmo at pose `G` (its centre at the scan's tree's centre): the scan drawn, and started
        from, at G @ inv(centre)."""
        with self._lock:
            if self.state.scan is None:
                return
            C_inv = np.eye(4)
            C_inv[:3, 3] = -self._centre()
            T = np.asarray(G, dtype=float) @ C_inv
            self.state = replace(self.state, moved=tuple(tuple(float(v) for v in row) for row in T))
            self._changed()

    # ---- refining ----------------------------------------------------------------------------------
    def start_pose(self) -> StartPose | None:
        """The fit of the pairs as a start pose (between the scans as their files give them), None
        until the pairs fix one."""
        with self._lock:
            name, fit, moved, n = self.state.scan, self.state.fit(), self.state.moved_pose(), len(self.state.pairs)
        if name is None or (moved is None and not fit.ok):
            return None
        T = moved if moved is not None else fit.T_ref_tgt
        snap = self.controller.snapshot
        names = [s.name for s in snap.scans]
        if name not in names:
            return None
        i = names.index(name)
        ref, tgt = snap.scan_item("prepare", 0, PreparedScan), snap.scan_item("prepare", i, PreparedScan)
        if ref is None or tgt is None:
            return None
        U = as_file_frames(T, ref_pose=snap.scans[0].pose, tgt_pose=snap.scans[i].pose,
                           ref_level=ref.T_level, tgt_level=tgt.T_level)
        U.setflags(write=False)
        how = "the scan moved by hand" if moved is not None else f"{n} point pairs picked by hand"
        return StartPose(T_ref_scan=U, source=f"{SOURCE} ({how})", reference=snap.scans[0].name)

    def refine(self) -> None:
        """Refine from here: the fit becomes the scan's start pose and the stages from coarse on run."""
        name = self.state.scan
        pose = self.start_pose()
        if name is None or pose is None or self.locked:
            return
        self.controller.start(name, pose)
        self.end()
        self.verdict_md.content = f"*Refining {md(name)} from your alignment…*"
        self._refined()

    def forget(self) -> None:
        name = str(self.scan_choice.value)
        if name in self.controller.snapshot.starts and not self.locked:
            self.controller.start(name, None)

    # ---- drawing and text ----------------------------------------------------------------------------
    def _show_controls(self, aligning: bool) -> None:
        self.scan_choice.disabled = aligning
        self.start_button.visible = not aligning
        self.stop_button.visible = aligning
        for h in (self.pair_choice, self.remove_button, self.clear_button, self.preview_box, self.gizmo_box,
                  self.refine_button):
            h.visible = aligning
        if aligning:
            self._show_pairs(self.state.fit())
        else:
            self.status_md.content = ""
            self.pairs_md.content = ""
            self.preview_box.value = False  # type: ignore[misc]
            self.gizmo_box.value = False  # type: ignore[misc]

    def _show_pairs(self, fit: PairFit) -> None:
        s = self.state
        name = md(s.scan or "")
        if s.ref_pick is not None:
            nxt = f"Now click the same point on **{name}** (right)."
        elif s.tgt_pick is not None:
            nxt = "Now click the same point on the **reference** (left)."
        else:
            nxt = f"Click a point on the reference (left) or on **{name}** (right)."
        self.status_md.content = f"{nxt} {md(fit.message)}"
        if s.pairs:
            rows = ["| pair | reference (m) | scan (m) | residual |", "|---|---|---|---|"]
            for k, p in enumerate(s.pairs):
                res = f"{fit.residuals_m[k] * 100:.1f} cm" if fit.ok else "–"
                rows.append(f"| {k + 1} | {_fmt(p.ref_xyz)} | {_fmt(p.tgt_xyz)} | {res} |")
            self.pairs_md.content = "\n".join(rows)
        else:
            self.pairs_md.content = ""
        options = tuple(f"Pair {k + 1}" for k in range(len(s.pairs))) or (NONE,)
        self.pair_choice.options = options
        self.remove_button.disabled = not s.pairs
        self.clear_button.disabled = not s.pairs
        self.preview_box.disabled = not fit.ok or s.moved is not None
        if self.preview_box.value != s.preview:
            self.preview_box.value = s.preview  # type: ignore[misc]
        self.refine_button.disabled = not fit.ok and s.moved is None
        if s.moved is not None:
            self.status_md.content += (" The scan stands where you moved it with the gizmo: *Refine from here* "
                                       "starts from there (untick the gizmo for the pairs' fit).")

    def _draw(self) -> None:
        """The two trees (the scan where it is drawn, `_D`) and the picks under /align."""
        name = self.state.scan
        if name is None:
            return
        snap = self.controller.snapshot
        i = [s.name for s in snap.scans].index(name) if name in [s.name for s in snap.scans] else 1
        key = (name, len(self._ref_pts), len(self._tgt_pts))
        if self._clouds_key != key:
            self._nodes["ref"] = self.scene.add_point_cloud(
                "/align/ref", self._ref_pts.astype(np.float32), scan_color(0), point_size=0.02, precision="float32")
            self._nodes["tgt"] = self.scene.add_point_cloud(
                "/align/tgt", self._tgt_pts.astype(np.float32), scan_color(i), point_size=0.02, precision="float32")
            self._clouds_key = key
        tgt = self._nodes["tgt"]
        kw = pose_kwargs(self._D)
        tgt.wxyz, tgt.position = kw["wxyz"], kw["position"]
        s = self.state

        def shown(p: Xyz) -> np.ndarray:
            out: np.ndarray = self._D[:3, :3] @ np.asarray(p) + self._D[:3, 3]
            return out

        for key_ in [k for k in self._nodes if k.startswith(("label", "mark"))]:
            self._nodes.pop(key_).remove()
        marks = [(f"r{k}", np.asarray(p.ref_xyz)) for k, p in enumerate(s.pairs)]
        marks += [(f"t{k}", shown(p.tgt_xyz)) for k, p in enumerate(s.pairs)]
        marks += [("rnext", np.asarray(s.ref_pick))] if s.ref_pick else []
        marks += [("tnext", shown(s.tgt_pick))] if s.tgt_pick else []
        for key_, at in marks:
            self._nodes[f"mark{key_}"] = self.scene.add_icosphere(
                f"/align/mark{key_}", radius=MARK_RADIUS_M, color=MARK_COLOUR, position=_xyz(at), cast_shadow=False)
        if s.pairs:
            segs = np.array([[p.ref_xyz, shown(p.tgt_xyz)] for p in s.pairs], dtype=np.float32)
            self._nodes["lines"] = self.scene.add_line_segments("/align/lines", segs, MARK_COLOUR, thickness=2.0,
                                                                 thickness_units="screen")
        elif "lines" in self._nodes:
            self._nodes.pop("lines").remove()
        for k, p in enumerate(s.pairs):
            for side, at in (("r", np.asarray(p.ref_xyz)), ("t", shown(p.tgt_xyz))):
                self._nodes[f"label{side}{k}"] = self.scene.add_label(
                    f"/align/label{side}{k}", f"{k + 1}", position=_xyz(at + np.array([0.0, 0.0, 0.15])))


def _fmt(p: Xyz) -> str:
    return ", ".join(f"{v:.2f}" for v in p)
