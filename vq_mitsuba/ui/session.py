"""What the browser editor holds: the view, the lighting, the selection and the edit history of
one run, and a render thread that draws a quick preview after every change and then refines it
while a page asks for frames (refining pauses `idle_s` seconds after the last request ends).

Reads the run through `run.run_dir`; edits are `models.material_edits.Edit`s, saved as `vq-mitsuba
edit` saves them, so a run saved here renders the same with `vq-mitsuba render`. Everything that
touches torch or Mitsuba runs on the render thread (one at a time); requests only change state.
"""

from __future__ import annotations

import math
import re
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from vq_mitsuba import brdf
from vq_mitsuba.data.cameras import Camera
from vq_mitsuba.data.imageio import linear_to_srgb
from vq_mitsuba.edit import parse_basecolor
from vq_mitsuba.run.run_dir import RunDir
from vq_mitsuba.errors import InputError, UserError, warn
from vq_mitsuba.models.material_edits import Change, Edit, Selection, apply_edits, check_change, material_library, \
    preset_changes
from vq_mitsuba.render.views import Renderer, material_colours, segmentation_overlay


PREVIEW = (2, 1)  # (spp, primary rays per pixel) of the first pass after a change
REFINE = (32, 4)  # the same for every later pass; passes average, weighted by their spp
MAX_SPP = 1024  # refining stops here
FRAME_TIMEOUT_S = 20.0  # a frame request waits at most this long for a newer frame
IDLE_S = 10.0  # refining pauses once no page has asked for a frame for this long
NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")


def display_modes() -> tuple[str, ...]:
    """The editor's display modes: a BRDF input's mode shows its map."""
    return ("render", "segmentation", *brdf.NAMES, "normal")


@dataclass
class Lighting:
    envmap: str = "fitted"  # "fitted" or a file name in the envmap folder
    rotate_deg: float = 0.0
    exposure_ev: float = 0.0


@dataclass
class Frame:
    version: int  # the state it shows
    spp: int  # samples per pixel accumulated
    png: bytes
    change_s: float  # seconds from the change it shows to this frame


@dataclass
class _Accum:
    """Running spp-weighted means of one view's images."""

    weight: float = 0.0
    coverage: float = 0.0
    images: dict = field(default_factory=dict)

    def add(self, images: dict, spp: int, aa: int) -> None:
        keys = ["rgb", "alpha", *brdf.NAMES, "normal"]
        for k in keys:
            v = images[k].astype(np.float64)
            self.images[k] = v * spp if k not in self.images else self.images[k] + v * spp
        if "material_share" in images:
            v = images["material_share"].astype(np.float64) * aa
            self.images["share"] = v if "share" not in self.images else self.images["share"] + v
        self.weight += spp
        self.coverage += aa

    def mean(self) -> dict:
        out = {k: v / self.weight for k, v in self.images.items() if k != "share"}
        if "share" in self.images:
            share = self.images["share"] / self.coverage
            ids = np.argmax(share[..., 1:], axis=-1) + 1
            out["material"] = np.where(out["alpha"] >= 0.5, ids, 0)
        return out


def orbit(to_world: np.ndarray, center: np.ndarray, up: np.ndarray, yaw_deg: float, pitch_deg: float,
          zoom: float = 1.0) -> np.ndarray:
    """A camera-to-world turned about `center`: by yaw about the world's up axis, by pitch about the
    camera's own horizontal axis (stopped 5 degrees short of the poles), then moved towards the
    centre by `zoom` (< 1 closer)."""

    def rotation(axis, deg):
        axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
        a = math.radians(deg)
        k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        return np.eye(3) + math.sin(a) * k + (1 - math.cos(a)) * k @ k

    m = np.array(to_world, np.float64)
    forward = m[:3, 2]
    elevation = math.degrees(math.asin(np.clip(-forward @ up, -1, 1)))  # > 0: looking down on the object
    pitch_deg = float(np.clip(elevation + pitch_deg, -85, 85) - elevation)
    rot = rotation(up, yaw_deg) @ rotation(m[:3, 0], pitch_deg)
    out = np.eye(4)
    out[:3, :3] = rot @ m[:3, :3]
    out[:3, 3] = center + zoom * (rot @ (m[:3, 3] - center))
    return out


def encode_png(image: np.ndarray) -> bytes:
    import imageio.v3 as iio

    return iio.imwrite("<bytes>", image, extension=".png")


class EditorSession:
    """The editor's state for one run, and the thread that renders it."""

    def __init__(self, run_dir: str | Path, envmap_dir: str | Path | None = None, size: int = 256,
                 max_spp: int = MAX_SPP, idle_s: float = IDLE_S):
        self.run = RunDir(run_dir)
        self.fitted = self.run.load()
        self._saved: set[Path] = set()  # the edited runs this editor saved (Save may replace them)
        self._save_lock = threading.Lock()
        self._materials_warned = False
        self.num_materials = self.fitted.num_materials
        self.materials = self._materials()  # the ranked materials as the page lists them
        self.size = int(size)
        self.max_spp = int(max_spp)  # refining stops here
        self.idle_s = float(idle_s)  # refining pauses once no frame was asked for this long
        self._waiting = 0  # frame requests waiting now
        self._asked_at = -math.inf  # when the last frame request ended (monotonic seconds)
        views = self.run.cameras()
        self.views = {c.name: c for split in views.values() for c in split}
        self.view_splits = {c.name: split for split, cams in views.items() for c in cams}
        first = views["train"][0]
        self.view_name = first.name
        self.camera = self._display_camera(first)
        bounds = np.asarray(self.fitted.mesh.bounds, np.float64)
        self.bounds = bounds
        self.center = bounds.mean(0)
        self.up = np.asarray(self.fitted.envmap_to_world, np.float64)[:3, 1]  # the lighting's up axis
        self.envmap_dir = Path(envmap_dir) if envmap_dir is not None else self._default_envmap_dir()
        self.lighting = Lighting()
        self.mode = "render"
        self.selection = Selection()
        self.history: list[list[Edit]] = [list(self.fitted.edits)]
        self.position = 0
        self.live = False  # the newest history entry is a slider still being dragged
        self.version = 0
        self.changed_at = time.perf_counter()
        self.frame: Frame | None = None
        self.message = ""
        self.job: dict | None = None  # the running or last export
        self._jobs: list = []
        self._cond = threading.Condition()
        self._stop = False
        self._thread: threading.Thread | None = None
        self._renderers: dict = {}
        self._accum: _Accum | None = None
        self._accum_version = -1
        self.last_images: dict | None = None  # the mean images of the shown frame (view's pixels)
        self.last_error = ""

    # --- setup ----------------------------------------------------------------------------------
    def _default_envmap_dir(self) -> Path | None:
        capture = Path(self.run.source().info()["capture"])
        folder = capture.parent / "envmaps"
        return folder if folder.is_dir() else None

    def _display_camera(self, camera: Camera) -> Camera:
        """The camera at the editor's resolution: its long side `size` pixels, same aspect and field."""
        scale = self.size / max(camera.width, camera.height)
        return camera.scaled(max(1, round(camera.width * scale)), max(1, round(camera.height * scale)))

    def envmaps(self) -> list[str]:
        if self.envmap_dir is None:
            return ["fitted"]
        files = sorted(p.name for p in self.envmap_dir.iterdir() if p.suffix.lower() in (".exr", ".hdr"))
        return ["fitted", *files]

    # --- the render thread ------------------------------------------------------------------------
    def start(self) -> None:
        self._thread = threading.Thread(target=self._loop, name="vq-mitsuba-ui-render", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=30)

    def _changed(self) -> None:
        """Call with the lock held after anything that changes what is drawn."""
        self.version += 1
        self.changed_at = time.perf_counter()
        self._cond.notify_all()

    def _redraw(self) -> None:
        """Call with the lock held after a change of the display mode or the selection: the shown
        frame's images drawn again as a new version, at once; refining goes on from them."""
        if self.frame is None or self.last_images is None:
            return
        self.version += 1
        self.frame = replace(self.frame, version=self.version,
                             png=encode_png(self.compose(self.last_images, self.mode, self.selection)))
        self._accum_version = self.version
        self._cond.notify_all()

    def _renderer(self, lighting: Lighting) -> Renderer:
        key = (lighting.envmap, lighting.rotate_deg, lighting.exposure_ev)
        if key not in self._renderers:
            envmap = None
            if lighting.envmap != "fitted":
                from vq_mitsuba.data.envmaps import load_envmap

                envmap = load_envmap(self.envmap_dir / lighting.envmap)
            # the run's lamps light its own envmap, turned or brighter too
            self._renderers = {key: Renderer(self.fitted, envmap, lighting.rotate_deg, lighting.exposure_ev,
                                             keep_lamps=envmap is None)}
        return self._renderers[key]

    def _watched(self) -> bool:
        """Call with the lock held: a page is waiting for a frame or asked for one lately."""
        return self._waiting > 0 or time.monotonic() - self._asked_at < self.idle_s

    def _loop(self) -> None:
        while True:
            with self._cond:
                # a change is always previewed (selecting a pixel needs its frame); refining needs a viewer
                while not self._stop and not self._jobs and self._accum_version == self.version \
                        and self._accum is not None and (self._accum.weight >= self.max_spp or not self._watched()):
                    self._cond.wait()  # a change, a job, a frame request or stop wakes it
                if self._stop:
                    return
                job = self._jobs.pop(0) if self._jobs else None
                version, camera, lighting = self.version, self.camera, replace(self.lighting)
                edits, mode, selection = list(self.history[self.position]), self.mode, self.selection
                fresh = self._accum_version != version or self._accum is None
                changed_at = self.changed_at
            if job is not None:
                self._run_job(job)
                continue
            try:
                self.fitted.edits = edits
                renderer = self._renderer(lighting)
                if fresh:
                    accum, (spp, aa), seed = _Accum(), PREVIEW, 0
                else:
                    accum, (spp, aa), seed = self._accum, REFINE, int(self._accum.coverage)
                images = renderer.render(camera, spp=spp, aa=aa, seed=seed)
            except Exception as exc:  # shown on the page; the editor keeps running
                with self._cond:
                    self.last_error = f"render failed: {exc}"
                    self.message = self.last_error
                    self._accum, self._accum_version = _Accum(weight=self.max_spp), version
                    self._cond.notify_all()
                continue
            with self._cond:
                if version != self.version:  # the state changed while rendering: start again
                    continue
                accum.add(images, spp, aa)
                self._accum, self._accum_version = accum, version
                mean = accum.mean()
                png = encode_png(self.compose(mean, mode, selection))
                self.last_images = mean
                self.frame = Frame(version, int(accum.weight), png, time.perf_counter() - changed_at)
                self._cond.notify_all()

    def _run_job(self, job) -> None:
        kind, fn = job
        try:
            result = fn()
            status = {"kind": kind, "state": "done", **result}
        except UserError as exc:
            status = {"kind": kind, "state": "failed", "error": str(exc)}
        except Exception as exc:
            status = {"kind": kind, "state": "failed", "error": f"{type(exc).__name__}: {exc}"}
        with self._cond:
            self.job = status
            self.message = status.get("error") or status.get("message", "")
            self._cond.notify_all()

    def wait_frame(self, after_version: int, after_spp: int, timeout: float = FRAME_TIMEOUT_S) -> Frame | None:
        """The newest frame once it differs from (after_version, after_spp); None on timeout."""
        deadline = time.monotonic() + timeout
        with self._cond:
            self._waiting += 1
            self._cond.notify_all()  # a paused refinement goes on
            try:
                while True:
                    f = self.frame
                    if f is not None and (f.version, f.spp) != (after_version, after_spp):
                        return f
                    left = deadline - time.monotonic()
                    if left <= 0 or self._stop:
                        return f
                    self._cond.wait(left)
            finally:
                self._waiting -= 1
                self._asked_at = time.monotonic()

    # --- what a frame shows -----------------------------------------------------------------------
    def compose(self, images: dict, mode: str, selection: Selection) -> np.ndarray:
        """The (H, W, 3) uint8 picture of one display mode, the selected materials outlined."""
        alpha = np.clip(images["alpha"], 0, 1)
        a = alpha[..., None]
        back = np.full(3, 0.16)
        if mode == "render":
            straight = images["rgb"] / np.maximum(a, 1e-6)
            rgb = linear_to_srgb(np.clip(straight, 0, None)) * a + back * (1 - a)
        elif mode == "segmentation" and "material" in images:
            rgb = segmentation_overlay(images["rgb"], alpha, images["material"]) * a + back * (1 - a)
        elif brdf.get(mode) is not None and brdf.get(mode).colour:
            rgb = linear_to_srgb(np.clip(images[mode], 0, 1)) * a + back * (1 - a)
        elif brdf.get(mode) is not None:  # a scalar, shown grey
            rgb = np.repeat(np.clip(images[mode], 0, 1)[..., None], 3, -1) * a + back * (1 - a)
        elif mode == "normal":
            rgb = (images["normal"] * 0.5 + 0.5) * a + back * (1 - a)
        else:  # segmentation of a run without a discrete branch
            rgb = linear_to_srgb(np.clip(images["rgb"] / np.maximum(a, 1e-6), 0, None)) * a + back * (1 - a)
        out = np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)
        if selection.materials and "material" in images:
            sel = np.isin(images["material"], selection.materials)
            inner = sel.copy()
            inner[1:, :] &= sel[:-1, :]
            inner[:-1, :] &= sel[1:, :]
            inner[:, 1:] &= sel[:, :-1]
            inner[:, :-1] &= sel[:, 1:]
            out[sel & ~inner] = (255, 220, 0)  # the selection's outline
        return out

    # --- requests (each changes state under the lock and returns what the page shows) -------------
    def state(self) -> dict:
        with self._cond:
            names = list(self.views)
            materials = self.materials
            edits = self.history[self.position]
            return {
                "run": self.run.dir.name, "world": self.fitted.world,
                "views": [{"name": n, "split": self.view_splits[n]} for n in names],
                "view": self.view_name, "width": self.camera.width, "height": self.camera.height,
                "modes": [m for m in display_modes() if m != "segmentation" or self.num_materials],
                "mode": self.mode,
                "envmaps": self.envmaps(), "lighting": vars(self.lighting),
                "lamps": 0 if self.fitted.lamps is None else len(self.fitted.lamps.position),
                "materials": self._materials_now(materials, edits, self.selection),
                "inputs": editor_inputs(),
                "presets": sorted(material_library()),
                "selection": self.selection.to_dict(),
                "bounds": self.bounds.tolist(),
                "edits": [e.label or _label(e) for e in edits],
                "can_undo": self.position > 0, "can_redo": self.position < len(self.history) - 1,
                "save_name": f"{self.run.dir.resolve().name}-edited",
                "job": self.job, "message": self.message,
                "refine_spp": REFINE[0] * 8 + PREVIEW[0], "max_spp": self.max_spp,
            }

    def _materials(self) -> list[dict]:
        if not self.num_materials:
            return []
        try:
            info = self.run.source().materials() or {}
        except InputError as exc:  # a product for people: render and export do without it, and so does the panel
            if not self._materials_warned:
                warn(f"{exc}; the material list shows no values")
                self._materials_warned = True
            info = {}
        listed = {int(m.get("id", i + 1)): m for i, m in enumerate(info.get("materials", []))}
        colours = material_colours(np.arange(1, self.num_materials + 1))
        out = []
        for k in range(1, self.num_materials + 1):
            c = colours[k - 1]
            out.append({"id": k, "colour": "#%02x%02x%02x" % tuple(int(round(x * 255)) for x in c),
                        **{key: listed.get(k, {}).get(key) for key in brdf.NAMES}})
        return out

    def _materials_now(self, materials: list[dict], edits: list[Edit], selection: Selection) -> list[dict]:
        """`materials` (the fitted values) with `edits` applied as the renderer applies them: an edit
        counts for material k when it selects k (or any material) and, if it has boxes, when the
        centre of the selection's box lies in one (without a box in the selection, box edits do
        not count: they change part of a material only)."""
        import torch

        known = [m for m in materials if all(m.get(k) is not None for k in brdf.NAMES)]
        if not edits or not known:
            return materials
        if selection.boxes:
            lo, hi = selection.boxes[0]
            point = [(a + b) / 2 for a, b in zip(lo, hi)]
        else:
            point = [math.nan] * 3  # inside no box
        values = {i.name: torch.tensor([m[i.name] for m in known], dtype=torch.float64) for i in brdf.INPUTS}
        ids = torch.tensor([m["id"] for m in known])
        points = torch.tensor([point] * len(known), dtype=torch.float64)
        now = apply_edits(edits, points, values, ids, self.fitted.cfg.field.roughness_min)
        values = {m["id"]: {i.name: now[i.name][k].tolist() if i.colour else float(now[i.name][k])
                            for i in brdf.INPUTS} for k, m in enumerate(known)}
        return [{**m, **values.get(m["id"], {})} for m in materials]

    def set_view(self, name: str) -> None:
        if name not in self.views:
            raise InputError(None, f"no view named '{name}'")
        with self._cond:
            self.view_name = name
            self.camera = self._display_camera(self.views[name])
            self._changed()

    def orbit_view(self, yaw_deg: float, pitch_deg: float, zoom: float = 1.0) -> None:
        values = (yaw_deg, pitch_deg, zoom)
        if not all(np.isfinite(values)) or not 0.2 <= zoom <= 5.0:
            raise InputError(None, f"orbit: yaw and pitch must be finite and zoom within 0.2..5, got {values}")
        with self._cond:
            to_world = orbit(self.camera.to_world, self.center, self.up, yaw_deg, pitch_deg, zoom)
            self.camera = replace(self.camera, name="orbit", to_world=to_world)
            self.view_name = "orbit"
            self._changed()

    def set_mode(self, mode: str) -> None:
        if mode not in display_modes():
            raise InputError(None, f"display mode '{mode}' is not one of {', '.join(display_modes())}")
        with self._cond:
            self.mode = mode
            self._redraw()

    def set_lighting(self, envmap: str, rotate_deg: float, exposure_ev: float) -> None:
        if envmap not in self.envmaps():
            raise InputError(None, f"no envmap '{envmap}' (one of {', '.join(self.envmaps())})")
        if not (np.isfinite(rotate_deg) and np.isfinite(exposure_ev) and abs(exposure_ev) <= 64):
            raise InputError(None, "lighting: rotation must be finite and exposure within -64..64 EV")
        with self._cond:
            self.lighting = Lighting(envmap, float(rotate_deg), float(exposure_ev))
            self._changed()

    def pixel_material(self, x: int, y: int) -> int:
        """The material id (1..M) the shown frame gives pixel (x, y): the majority of its primary rays."""
        with self._cond:
            # the frame must show the current view: after an orbit, wait for its first frame
            self._cond.wait_for(lambda: self._accum_version == self.version or self._stop, timeout=FRAME_TIMEOUT_S)
            images = self.last_images
            if self.num_materials is None:
                raise InputError(None, "this run has no discrete branch: select with a box")
            if images is None:
                raise InputError(None, "no frame drawn yet")
            h, w = images["alpha"].shape
            if not (0 <= x < w and 0 <= y < h):
                raise InputError(None, f"pixel {x},{y} lies outside the {w}x{h} view")
            k = int(images["material"][y, x])
            if k == 0:
                raise InputError(None, f"pixel {x},{y} shows the background, not the object")
            return k

    def select(self, materials: list[int] | None = None, box=None, pixel: tuple[int, int] | None = None,
               add: bool = False) -> Selection:
        """Set the selection: material ids, a pixel's material, and / or a world box (None: no box)."""
        ids = [int(k) for k in (materials or [])]
        if pixel is not None:
            ids.append(self.pixel_material(int(pixel[0]), int(pixel[1])))
        m = self.num_materials or 0
        bad = [k for k in ids if not 1 <= k <= m]
        if bad:
            raise InputError(None, f"material {bad[0]}: the run has materials 1..{m}" if m
                             else "this run has no discrete branch: select with a box")
        boxes = ()
        if box is not None:
            lo, hi = (tuple(float(v) for v in corner) for corner in box)
            if len(lo) != 3 or len(hi) != 3 or not all(np.isfinite(lo + hi)):
                raise InputError(None, f"box: two corners of three finite numbers, got {box}")
            boxes = ((tuple(map(min, lo, hi)), tuple(map(max, lo, hi))),)
        with self._cond:
            if add:
                ids = list(self.selection.materials) + ids
            self.selection = Selection(tuple(dict.fromkeys(ids)), boxes)
            self.live = False
            self._redraw()  # outline the selection at once
            return self.selection

    def edit(self, changes: list[dict] | None = None, preset: str | None = None, live: bool = False) -> Edit:
        """Add an edit of the selection. `live`: a slider being dragged; the next change of the same
        keys on the same selection replaces this entry instead of adding one."""
        parsed = preset_changes(preset) if preset else []
        as_typed = {}
        for c in changes or []:
            try:
                value = c["value"]
                inp = brdf.get(c.get("key"))
                if isinstance(value, str) and inp is not None and inp.colour:  # "#RRGGBB" from a colour picker
                    as_typed[inp.name] = value.strip()
                    value = parse_basecolor(value)
                value = _numbers(c.get("key"), value)
                parsed.append(check_change(Change(str(c.get("op", "set")), str(c["key"]), value)))
            except KeyError as exc:
                raise InputError(None, f"a change without {exc}: give 'key' and 'value'") from None
            except (TypeError, ValueError) as exc:
                raise InputError(None, str(exc)) from None
        if not parsed:
            raise InputError(None, "no change given")
        with self._cond:
            sel = self.selection
            if not (sel.materials or sel.boxes):
                raise InputError(None, "select a material (click it) or a box first")
            edit = Edit(sel, parsed)
            edit.label = _label(edit, preset, as_typed)
            current = self.history[self.position]
            same = (self.live and current and current[-1].selection == sel
                    and {c.key for c in current[-1].changes} == {c.key for c in parsed})
            if same:
                self.history[self.position] = current[:-1] + [edit]
            else:
                del self.history[self.position + 1:]
                self.history.append(current + [edit])
                self.position += 1
            self.live = bool(live)
            self._changed()
            return edit

    def undo(self) -> None:
        with self._cond:
            if self.position == 0:
                raise InputError(None, "nothing to undo")
            self.position -= 1
            self.live = False
            self._changed()

    def redo(self) -> None:
        with self._cond:
            if self.position >= len(self.history) - 1:
                raise InputError(None, "nothing to redo")
            self.position += 1
            self.live = False
            self._changed()

    def edits(self) -> list[Edit]:
        with self._cond:
            return list(self.history[self.position])

    def _target(self, name: str) -> RunDir:
        if not NAME.match(name or "") or name in (".", ".."):
            raise InputError(None, f"'{name}' is not a folder name (letters, digits, '.', '_', '-')")
        target = RunDir(self.run.dir.resolve().parent / name)
        if target.dir.exists() and not target.dir.is_dir():
            raise InputError(target.dir, "is a file, not a folder: save under another name")
        if target.dir.resolve() in (self.run.dir.resolve(), self.run.source().dir.resolve()):
            raise InputError(target.dir, "is the run being edited: save under another name")
        if (target / RunDir.INFO).is_file() and not target.is_edit():
            raise InputError(target.dir, "holds a fitted run: save under another name")
        if (target / RunDir.INFO).is_file() and target.dir.resolve() not in self._saved:
            raise InputError(target.dir, "holds an edit list this editor did not save: save under another name")
        if target.dir.exists() and not (target / RunDir.INFO).is_file() and any(target.dir.iterdir()):
            raise InputError(target.dir, "is a non-empty folder that is not a run: save under another name")
        return target

    def save(self, name: str) -> RunDir:
        """Write the edit list as an edited run NAME beside the run (what `vq-mitsuba edit` writes)."""
        with self._save_lock:  # one save at a time: a concurrent one of the same name sees this one's
            target = self._target(name)
            target.write_edit(self.run, self.edits())
            self._saved.add(target.dir.resolve())
        with self._cond:
            self.message = f"saved {target.dir}"
        return target

    def export(self, name: str, fmt: str, texture_size: int = 1024) -> None:
        """Save as NAME, then export it as FORMAT into NAME/export-FORMAT (on the render thread)."""
        from vq_mitsuba.export.formats import FORMATS, check_texture_size, export_run
        from vq_mitsuba.messages import quiet

        if fmt not in FORMATS:
            raise InputError(None, f"unknown export format '{fmt}' (one of {', '.join(FORMATS)})")
        check_texture_size(texture_size)  # before the save: a refused export writes nothing
        target = self.save(name)
        out = target.dir / f"export-{fmt}"

        def job():
            with quiet():  # the editor shows the job's state, not the bake's bar
                summary = export_run(target.dir, fmt, out, texture_size=texture_size)
            return {"message": f"exported {out}", "path": str(out), "files": summary.get("files", [])}

        with self._cond:
            self.job = {"kind": "export", "state": "running", "path": str(out)}
            self.message = f"exporting {fmt} to {out} ..."
            self._jobs.append(("export", job))
            self._cond.notify_all()


def editor_inputs() -> list[dict]:
    """The BRDF inputs as the page builds its controls from them: name, channels, range, a
    slider's step and first value."""
    return [{"name": i.name, "channels": i.channels, "low": i.low, "high": i.high, "step": i.step,
             "default": i.default} for i in brdf.INPUTS]


def _numbers(key, value):
    """A change's value as a float, or three for a colour; ValueError naming the key otherwise."""
    try:
        if any(isinstance(v, bool) for v in (value if isinstance(value, (list, tuple)) else [value])):
            raise TypeError("true and false are not numbers")
        return tuple(float(v) for v in value) if isinstance(value, (list, tuple)) else float(value)
    except (TypeError, ValueError, OverflowError):  # OverflowError: an integer beyond any float
        raise ValueError(f"the value of '{key}' must be a number (three for a colour), got {value!r}") from None


def _fmt(v: float) -> str:
    return f"{v:.3g}"


def _label(edit: Edit, preset: str | None = None, as_typed: dict | None = None) -> str:
    """The edit as `vq-mitsuba edit` arguments, e.g. "--material 2 --set roughness=0.3" (values in
    `as_typed`, e.g. a colour as "#RRGGBB", as the user gave them)."""
    parts = [f"--material {k}" for k in edit.selection.materials]
    parts += ["--box " + ",".join(_fmt(v) for v in lo + hi) for lo, hi in edit.selection.boxes]
    if preset:
        parts.append(f"--preset {preset}")
    else:
        for c in edit.changes:
            value = ",".join(_fmt(v) for v in c.value) if isinstance(c.value, tuple) else _fmt(c.value)
            value = (as_typed or {}).get(c.key, value) if c.op == "set" else value
            parts.append(f"--{c.op.replace('_', '-')} {c.key}={value}" if c.op != "hue_shift" else f"--hue-shift {value}")
    return " ".join(parts)
