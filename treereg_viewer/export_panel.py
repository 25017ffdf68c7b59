"""The "Files" tab: exports (browser downloads and, with --out, files on disk) and parameter files."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import viser

from treereg_core import params as P
from treereg_core.errors import ConfigError, OutputError, ScanError
from treereg_core.io.json_input import parse_json
from treereg_core.io.start import STARTS_KEY

from . import export
from .actions import AppActions
from .align import saved_start_poses
from .checks import stage_warnings
from .presets import ABOUT_SHORT, preset_note
from .text import md
from .uploads import discard

#: A parameter file is a few kB.
PARAMS_MAX_BYTES = 1000 * 1000

log = logging.getLogger(__name__)


class ExportPanel:
    def __init__(self, gui: viser.GuiApi, app: AppActions) -> None:
        self.app = app
        with gui.add_folder("Export"):
            where = f" They are also written to {md(app.out_dir)}." if app.out_dir else ""
            gui.add_markdown(
                "The transforms `T_ref_scan` of the latest run: each scan's final placement (*11 Placement*: all scans solved together from the verified fine registrations; only coarse if that is all that ran), with the "
                "parameters used; CloudCompare matrix text per scan; the PDAL matrix string; the merged "
                f"registered cloud, each point tagged with its scan. A click starts the download.{where}"
            )
            self.cloud_format = gui.add_dropdown("Merged cloud format", ("ply", "las"), initial_value="ply",
                                                 hint="Each point carries its scan's number: PLY property scan_id, "
                                                 "LAS point_source_id (1 = the reference).")
            self.keep_unverified = gui.add_checkbox(
                "Include unverified best guesses", False,
                hint="Unverified scans are left out of transforms.json's \"transforms\" and the merged cloud (listed "
                     "under \"unverified\" with the reasons); tick this to export their best guesses too, marked as such.")
            self.download_transforms = gui.add_button("Download transforms.json", icon=viser.Icon.DOWNLOAD)
            self.download_cloud = gui.add_button("Download the merged cloud", icon=viser.Icon.DOWNLOAD)
            self.download_all = gui.add_button("Download all exports (zip)", icon=viser.Icon.FILE_ZIP)
            self.export_md = gui.add_markdown("")
        self.download_transforms.on_click(lambda e: self._download(e.client, only="transforms.json"))
        self.download_cloud.on_click(lambda e: self._download(e.client, only=f"merged.{self.cloud_format.value}"))
        self.download_all.on_click(lambda e: self._download(e.client, only=None))
        with gui.add_folder("Parameters"):
            # Started with `--preset paper` (or a config equal to a preset): show that preset.
            current = next((n for n, pr in P.PRESETS.items() if pr == app.controller.params), "robust")
            self.preset = gui.add_dropdown("Preset", tuple(P.PRESETS), initial_value=current,
                                           hint="robust: our defaults; paper: the paper's settings taken literally.")
            self.preset_md = gui.add_markdown(preset_note(self.preset.value))
            self.apply_preset = gui.add_button("Apply preset")
            self.download_params = gui.add_button("Download parameters (JSON)", icon=viser.Icon.DOWNLOAD)
            self.load_params = gui.add_upload_button("Load parameters (JSON)", icon=viser.Icon.UPLOAD,
                                                     mime_type="application/json")
        self.preset.on_update(lambda _: setattr(self.preset_md, "content", preset_note(self.preset.value)))
        self.apply_preset.on_click(lambda _: app.load_params(P.PRESETS[self.preset.value], f"preset {self.preset.value}",
                                                             ABOUT_SHORT.get(self.preset.value, "")))
        self.download_params.on_click(lambda e: self._download_params(e.client))
        app.uploads.add(self.load_params, self._load_params, PARAMS_MAX_BYTES, what="parameter file")
        if current in ABOUT_SHORT and app.controller.params == P.PRESETS[current]:
            app.controller.note(ABOUT_SHORT[current])  # e.g. why the paper preset may fail

    def _download(self, client: Any, only: str | None) -> None:
        self.app.flush_edits()
        snap = self.app.controller.snapshot
        try:
            bundle = export.export_bundle(snap, cloud_format=self.cloud_format.value,
                                          keep_unverified=bool(self.keep_unverified.value))
            written, loaded = "", [s.source for s in snap.scans if s.source is not None]
            # An export never replaces a loaded scan (merged.ply in the --out folder): not written, still downloaded.
            clash = export.input_clash(bundle, self.app.out_dir, loaded) if self.app.out_dir is not None else None
            if clash:
                written = f" ⚠ Not written to {self.app.out_dir}: {clash}; the download has every file."
            elif self.app.out_dir is not None:
                paths = export.write_bundle(bundle, self.app.out_dir, loaded)
                written = f" Written to {self.app.out_dir} ({len(paths)} files)."
        except (export.ExportError, ConfigError, ScanError, OutputError, OSError) as e:
            self._failed(str(e))
            return
        except Exception as e:  # a writer bug: one line for the user, the traceback in the log
            log.exception("export failed")
            self._failed(f"{type(e).__name__}: {e}")
            return
        if only is not None:
            self.app.send_file(client, only, bundle.files[only])
        else:
            # Named by what is inside: the case, the registration, the cloud's format (PLY or LAS).
            self.app.send_file(client, export.zip_name(snap, bundle, self.cloud_format.value), export.zip_bundle(bundle))
        warned = stage_warnings(snap)
        caution = (" **⚠ These transforms carry warnings (see the message at the top): check them before use.**"
                   if warned else "")
        left_out = [n for n, (v, _, _) in snap.verdicts.items() if v != "verified" and n not in bundle.transforms]
        kept = [n for n, (v, _, _) in snap.verdicts.items() if v != "verified" and n in bundle.transforms]
        what = (f"Exported the transforms of {len(bundle.transforms)} scans"
                + (f", {len(kept)} of them unverified best guesses ({', '.join(kept)})" if kept else "") + ".")
        if left_out:
            what += (f" Not exported: {', '.join(left_out)} (not verified; see the Placement stage) — tick "
                     "\"Include unverified best guesses\" to export them anyway.")
        # Plain text for the message at the top (it replaces an "Export failed" from before), escaped here.
        self.export_md.content = f"{md(what + written)}{caution}"
        self.app.controller.note(f"{what}{written}", error=bool(clash))

    def _failed(self, why: str) -> None:
        self.export_md.content = f"**⚠ Export failed:** {md(why)}"
        self.app.controller.note(f"Export failed: {why}", error=True)

    def _download_params(self, client: Any) -> None:
        self.app.flush_edits()  # a value just typed belongs in the file
        # The start poses in force go beside the parameters (`export.params_file`).
        data = export.params_file(self.app.controller.params, self.app.controller.snapshot)
        self.app.send_file(client, "params.json", data)

    def _load_params(self, filename: str, path: Path) -> None:
        """A parameter file received from the browser: applied when valid, else one message. The start
        poses it carries (a params.json the app saved: `export.params_file`) are given again to the
        loaded scans it names, to run with the parameters when Run is pressed."""
        try:
            data = path.read_bytes()
            try:
                doc = parse_json(data, filename)
                params = P.from_dict(doc, source=filename)
                names = [s.name for s in self.app.controller.snapshot.scans]
                poses, absent = (saved_start_poses(path, filename, doc, names)
                                 if isinstance(doc, dict) and STARTS_KEY in doc else ([], []))
            except ConfigError as e:
                self.app.controller.note(f"{str(e).replace(str(path), filename)}; the parameters in force did not change.",
                                         error=True)
                return
        finally:
            discard(path)
        note = ""
        if poses:
            note = f"Start poses restored for {', '.join(n for n, _ in poses)}."
        if absent:
            note += f" Start poses of {', '.join(absent)} not restored: no such scan is loaded."
        for n, pose in poses:  # before the parameters' note, which then says what was loaded
            self.app.controller.start(n, pose, run=False)
        self.app.load_params(params, filename, note.strip())
