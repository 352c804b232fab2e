"""A synthetic dataset's folder: every file `vq-mitsuba make-scene` writes and `eval` reads, in one place.

A dataset folder holds (both renderers, Mitsuba and Cycles, write the same layout):

    transforms_train.json, transforms_test.json   NeRF-synthetic cameras, Blender world
    mesh.ply                                      all shapes merged, Blender world
    scene.xml, scene_test.xml                     the same scene in Mitsuba world (Y up), no emitter
    meshes/<shape>.ply                            Mitsuba world (vertex_color attribute if textured)
    images/<id>.exr, images/<id>.png              train and test views under envmaps/train.exr
    gt/<id>_{basecolor,metallic,roughness,normal}.exr, gt/<id>_{material,alpha}.png   test views
    relit/<env>/<id>.exr, .png                    test views under each held-aside envmap
    envmaps/train.exr, envmaps/<env>.exr          lat-long maps, Blender convention
    neus/, colmap/, colmap_opencv/, nerfstudio/, llff/   the training views as photographed captures
                                                  (--photo-formats)
    scene.json                                    metadata, written last
    .make-scene-incomplete                        while make-scene writes the folder
    _cycles/job.json, _cycles/...                 the Cycles worker's job and raw renders (kept on request)

Images: EXR is linear RGBA with premultiplied colour (OpenEXR's convention; background 0),
PNG is sRGB RGBA with straight (un-premultiplied) colour and alpha = pixel coverage.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from vq_mitsuba import brdf
from vq_mitsuba.data.formats import mitsuba_xml, nerf_synthetic
from vq_mitsuba.data.imageio import write_exr, write_png, written
from vq_mitsuba.errors import InputError


def write_rgba(stem: str | Path, rgba: np.ndarray) -> None:
    """A rendered view as STEM.exr (linear, premultiplied; non-finite values 0, colour >= 0, alpha
    in [0, 1]) and STEM.png (sRGB, straight colour, alpha = coverage)."""
    stem = Path(stem)
    rgba = np.asarray(rgba, dtype=np.float32)
    rgba = np.nan_to_num(rgba, nan=0.0, posinf=0.0, neginf=0.0)
    rgba[..., :3] = np.maximum(rgba[..., :3], 0.0)
    rgba[..., 3] = np.clip(rgba[..., 3], 0.0, 1.0)
    write_exr(stem.with_suffix(".exr"), rgba)
    a = rgba[..., 3]
    straight = rgba[..., :3] / np.maximum(a, 1e-6)[..., None]
    straight = np.where(a[..., None] > 0, straight, 0.0)
    write_png(stem.with_suffix(".png"), straight, alpha=a)


def write_gt(stem: str | Path, gt: dict) -> None:
    """A test view's ground-truth maps: STEM_<input>.exr of each BRDF input, STEM_normal.exr,
    STEM_material.png (ids), STEM_alpha.png (coverage)."""
    for kind in DatasetDir.GT_EXR:
        write_exr(f"{stem}_{kind}.exr", gt[kind])
    write_png(f"{stem}_material.png", gt["material"])
    write_png(f"{stem}_alpha.png", gt["alpha"], srgb=False)


def _plain_name(value) -> bool:
    return isinstance(value, str) and value not in ("", ".", "..") and not any(c in value for c in "/\\\0")


class DatasetDir:
    INFO = "scene.json"
    TRANSFORMS_TRAIN = nerf_synthetic.SPLIT_FILE.format("train")  # the two captures of a dataset: NeRF-synthetic
    TRANSFORMS_TEST = nerf_synthetic.SPLIT_FILE.format("test")
    MESH = "mesh.ply"
    SCENE_XML = mitsuba_xml.FOLDER_FILES[0]  # and a Mitsuba scene
    SCENE_TEST_XML = "scene_test.xml"
    MESHES = "meshes"
    IMAGES = "images"
    GT = "gt"
    RELIT = "relit"
    ENVMAPS = "envmaps"
    TRAIN_ENVMAP = "train"  # envmaps/train.exr lights images/
    INCOMPLETE = ".make-scene-incomplete"  # in a dataset folder while make-scene writes it
    CYCLES_WORK = "_cycles"  # the Cycles worker's job file and raw multilayer EXRs (removed unless kept)
    CYCLES_JOB = "job.json"
    SUBDIRS = (IMAGES, GT, MESHES, ENVMAPS, RELIT)  # a dataset's folders, emptied by each make-scene
    GT_EXR = (*brdf.NAMES, "normal")  # gt/<id>_<kind>.exr: each BRDF input's map and the normal
    GT_PNG = ("material", "alpha")  # gt/<id>_<kind>.png
    PHOTO_FORMATS = ("neus", "colmap", "colmap_opencv", "nerfstudio", "llff")  # --photo-formats' folders
    # Everything make-scene writes at the top of a dataset folder: an earlier dataset is replaced whole.
    OWN_ENTRIES = (INFO, INCOMPLETE, TRANSFORMS_TRAIN, TRANSFORMS_TEST, MESH, SCENE_XML, SCENE_TEST_XML,
                   *SUBDIRS, *PHOTO_FORMATS, CYCLES_WORK)

    def __init__(self, path: str | Path):
        self.dir = Path(path)

    def __truediv__(self, name: str) -> Path:
        return self.dir / name

    def __repr__(self) -> str:
        return f"DatasetDir({str(self.dir)!r})"

    @classmethod
    def find(cls, path: str | Path) -> DatasetDir:
        """The dataset of a folder or of any file inside it (scene.json, scene.xml, transforms json);
        InputError when it is missing or not a whole make-scene dataset."""
        path = Path(path)
        if not path.exists():
            raise InputError(path, "dataset folder not found")
        root = path if path.is_dir() else path.parent
        for name in (cls.INFO, cls.TRANSFORMS_TEST):
            if not (root / name).is_file():
                raise InputError(root / name, "not a dataset written by `vq-mitsuba make-scene` (file missing)")
        return cls(root)

    # --- paths ---------------------------------------------------------------------------------
    @property
    def info_path(self) -> Path:
        return self.dir / self.INFO

    def is_dataset(self) -> bool:
        """scene.json is there: make-scene finished writing the folder."""
        return self.info_path.is_file()

    def image(self, name: str, env: str | None = None) -> Path:
        """A view's stem (no suffix): images/<name>, or relit/<env>/<name> under a held-aside envmap."""
        return (self.relit_dir(env) if env is not None else self.dir / self.IMAGES) / name

    def relit_dir(self, env: str) -> Path:
        return self.dir / self.RELIT / env

    def gt(self, name: str, kind: str) -> Path:
        """gt/<name>_<kind>.exr (GT_EXR) or .png (GT_PNG) of a test view."""
        suffix = ".exr" if kind in self.GT_EXR else ".png" if kind in self.GT_PNG else None
        if suffix is None:
            raise ValueError(f"no ground-truth map '{kind}'")
        return self.dir / self.GT / f"{name}_{kind}{suffix}"

    def gt_stem(self, name: str) -> Path:
        return self.dir / self.GT / name

    @classmethod
    def envmap_file(cls, env: str) -> str:
        """envmaps/<env>.exr, relative to the dataset (as scene.json names it)."""
        return f"{cls.ENVMAPS}/{env}.exr"

    def envmap(self, env: str) -> Path:
        return self.dir / self.envmap_file(env)

    @classmethod
    def shape_file(cls, shape: str) -> str:
        """meshes/<shape>.ply, relative to the dataset (as scene.xml and scene.json name it)."""
        return f"{cls.MESHES}/{shape}.ply"

    def shape_mesh(self, shape: str) -> Path:
        return self.dir / self.shape_file(shape)

    @classmethod
    def frame_file(cls, name: str) -> str:
        """A transforms json frame's file_path: ./images/<name>."""
        return f"./{cls.IMAGES}/{name}"

    @property
    def cycles_work_dir(self) -> Path:
        return self.dir / self.CYCLES_WORK

    # --- writing -------------------------------------------------------------------------------
    def prepare(self, subdirs: tuple[str, ...] = SUBDIRS) -> Path:
        """The folder with its `subdirs` made; where it holds an earlier make-scene output
        (scene.json, or the mark of an unfinished one), that output is removed first, whole (every
        entry of OWN_ENTRIES, the photographed captures too), so nothing of it survives beside the new one."""
        out = self.dir
        if self.is_dataset() or (out / self.INCOMPLETE).is_file():
            for name in self.OWN_ENTRIES:
                entry = out / name
                if name in (self.INFO, self.INCOMPLETE):
                    continue  # scene.json goes with mark_incomplete; the mark stays until the end
                if entry.is_dir() and not entry.is_symlink():
                    shutil.rmtree(entry, ignore_errors=True)
                elif entry.exists() or entry.is_symlink():
                    entry.unlink()
        for sub in subdirs:
            (out / sub).mkdir(parents=True, exist_ok=True)
        return out

    def check_replaceable(self, command: str = "make-scene") -> None:
        """Refuse (InputError naming the folder and what it holds) to write a dataset into this
        existing, non-empty folder unless it is provably an earlier make-scene output: the mark of an
        unfinished one or a readable scene.json of make-scene's, and nothing beside the entries a
        dataset holds (OWN_ENTRIES). `prepare` then replaces it whole."""
        entries = sorted(p.name + ("/" if p.is_dir() else "") for p in self.dir.iterdir())
        shown = ", ".join(entries[:6]) + (f", ... {len(entries)} in all" if len(entries) > 6 else "")
        if not (self.dir / self.INCOMPLETE).is_file():
            try:
                meta = json.loads(self.info_path.read_text())
            except (OSError, ValueError, RecursionError) as exc:  # RecursionError: nested too deep
                meta = exc
            if not isinstance(meta, dict) or not {"name", "resolution"} <= meta.keys():
                why = f"cannot be read ({meta})" if isinstance(meta, Exception) else "is not make-scene's"
                raise InputError(self.dir, f"holds {shown}, and its {self.INFO} {why}: {command} cannot tell this "
                                           "is a dataset it made, and would mix its files with these; move the "
                                           "folder away or choose a new one with -o")
        other = sorted(name for name in entries if name.rstrip("/") not in self.OWN_ENTRIES)
        if other:
            listed = ", ".join(other[:3]) + (", ..." if len(other) > 3 else "")
            raise InputError(self.dir, f"holds files {command} did not write ({listed}) beside an earlier dataset: "
                                       f"{command} replaces that dataset whole; move them away or choose a new "
                                       "folder with -o")

    def mark_incomplete(self) -> None:
        """Mark the folder as being written, and drop an earlier dataset's scene.json (written again last)."""
        mark = self.dir / self.INCOMPLETE
        written(mark, lambda: mark.write_text("make-scene did not finish writing this folder\n"))
        self.info_path.unlink(missing_ok=True)

    def mark_complete(self) -> None:
        (self.dir / self.INCOMPLETE).unlink()

    def write_view(self, name: str, rgba: np.ndarray, env: str | None = None) -> None:
        """images/<name>.exr and .png (or relit/<env>/<name>.*): see `write_rgba`."""
        write_rgba(self.image(name, env), rgba)

    def write_gt(self, name: str, gt: dict) -> None:
        write_gt(self.gt_stem(name), gt)

    def write_info(self, meta: dict) -> None:
        written(self.info_path, lambda: self.info_path.write_text(json.dumps(meta, indent=2)))

    # --- reading -------------------------------------------------------------------------------
    def info(self) -> dict:
        """scene.json, checked where evaluation reads it: an object whose `relight` (when given)
        lists {"name": NAME, "file": PATH} with plain names, and whose `materials` list
        {"id": N, "name": TEXT}; InputError naming the file and the entry otherwise."""
        path = self.info_path
        try:
            meta = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise InputError(path, f"not valid JSON ({exc})") from None
        except RecursionError:  # [[[[... deeper than the parser goes
            raise InputError(path, "not valid JSON (lists or objects nested too deep)") from None
        if not isinstance(meta, dict):
            raise InputError(path, "expected a JSON object (the dataset's description)")
        relight = meta.get("relight")
        if relight is not None:
            if not isinstance(relight, list):
                raise InputError(path, "'relight' must be a list of {\"name\": ..., \"file\": ...}")
            for i, e in enumerate(relight):
                if not isinstance(e, dict) or not _plain_name(e.get("name")) or not isinstance(e.get("file", ""), str):
                    raise InputError(path, f"relight[{i}] must be {{\"name\": NAME, \"file\": PATH}} with a plain "
                                           f"name (no folders), got {json.dumps(e)[:80]}")
        materials = meta.get("materials", [])
        if not isinstance(materials, list):
            raise InputError(path, "'materials' must be a list of {\"id\": N, \"name\": ...}")
        for i, m in enumerate(materials):
            if not isinstance(m, dict) or ("id" in m and (isinstance(m["id"], bool) or not isinstance(m["id"], int))):
                raise InputError(path, f"materials[{i}] must be {{\"id\": N, \"name\": ...}} with a whole-number id, "
                                       f"got {json.dumps(m)[:80]}")
        return meta

    def relight_envs(self, meta: dict) -> list[tuple[str, Path]]:
        """(name, envmap path) of every relighting condition of scene.json (`meta`), each envmap on
        disk; a dataset whose scene.json lists none has those of its relit/ folders."""
        entries = meta.get("relight")
        if entries is None:  # older datasets: discover them
            entries = [{"name": p.name, "file": self.envmap_file(p.name)}
                       for p in sorted((self.dir / self.RELIT).glob("*")) if p.is_dir()]
        out = []
        for e in entries:
            env_path = self.dir / e.get("file", self.envmap_file(e["name"]))
            if not env_path.is_file():
                raise InputError(env_path, f"envmap of relighting condition '{e['name']}' missing")
            out.append((e["name"], env_path))
        return out
