"""Pinhole cameras in Mitsuba's convention and conversions from other conventions.

Mitsuba cameras look along local +Z with +Y up and +X to the left. A NeRF-synthetic /
Blender frame (OpenGL axes: -Z forward, +Y up, +X right) converts by flipping X and Z.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

# Blender world (Z up) from Mitsuba's lat-long envmap frame (Y up): applied as the envmap's
# to_world, the same EXR lights a Blender-world scene as Cycles does.
BLENDER_ENV_TO_WORLD = np.array(
    [[0, 0, 1, 0], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=np.float64
)
MITSUBA_TO_BLENDER = BLENDER_ENV_TO_WORLD[:3, :3]  # Blender world = this @ Mitsuba world
OPENGL_TO_MITSUBA = np.diag([-1.0, 1.0, -1.0, 1.0])
# OpenCV camera axes (COLMAP, IDR: +X right, +Y down, +Z forward) to Mitsuba's (+X left, +Y up).
OPENCV_TO_MITSUBA = np.diag([-1.0, -1.0, 1.0, 1.0])


@dataclass
class Camera:
    """A pinhole camera: `to_world` maps Mitsuba camera space (+Z forward, +Y up, +X left).

    The focal length along x follows from `fov_x_deg` and `width`; photographed captures may have
    a different focal length along y (`focal_y_ratio` = fy / fx) and a principal point off the
    image centre (`principal`, pixels, x right and y down, pixel centres at +0.5)."""

    name: str
    to_world: np.ndarray  # (4, 4) float64
    fov_x_deg: float  # horizontal field of view
    width: int
    height: int
    focal_y_ratio: float = 1.0  # fy / fx
    principal: tuple[float, float] | None = None  # (cx, cy) in pixels; None: the image centre

    @property
    def origin(self) -> np.ndarray:
        return self.to_world[:3, 3]

    def focal_px(self) -> float:
        return 0.5 * self.width / math.tan(0.5 * math.radians(self.fov_x_deg))

    def intrinsics(self) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy) in pixels."""
        fx = self.focal_px()
        cx, cy = self.principal if self.principal is not None else (0.5 * self.width, 0.5 * self.height)
        return fx, fx * self.focal_y_ratio, float(cx), float(cy)

    def scaled(self, width: int, height: int) -> Camera:
        """The same camera with an image of width x height pixels (the field of view kept)."""
        principal = None
        if self.principal is not None:
            principal = (self.principal[0] * width / self.width, self.principal[1] * height / self.height)
        ratio = self.focal_y_ratio * (height / self.height) / (width / self.width)
        return replace(self, width=int(width), height=int(height), principal=principal, focal_y_ratio=ratio)

    def projection(self) -> np.ndarray:
        """The (3, 4) matrix taking homogeneous world points to homogeneous pixels (x right, y down;
        pixel centres at +0.5); the third coordinate is the depth, positive in front of the camera."""
        fx, fy, cx, cy = self.intrinsics()
        # +X is left and +Y up in Mitsuba camera space, so image x grows towards -X and y towards -Y.
        k = np.array([[-fx, 0.0, cx], [0.0, -fy, cy], [0.0, 0.0, 1.0]])
        return k @ np.linalg.inv(self.to_world)[:3]

    def project(self, points_world: np.ndarray) -> np.ndarray:
        """Pixel coordinates (x right, y down; pixel centres at +0.5) of world points (N, 3)."""
        pts = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        proj = self.projection()
        hom = pts @ proj[:, :3].T + proj[:, 3]
        return hom[:, :2] / hom[:, 2:]

    def principal_offset(self) -> tuple[float, float]:
        """Mitsuba's principal_point_offset_x / _y: the principal point's offset from the image centre
        as a fraction of the width / height, positive towards the left / top."""
        _, _, cx, cy = self.intrinsics()
        return (0.5 * self.width - cx) / self.width, (0.5 * self.height - cy) / self.height

    def to_mitsuba_dict(self, spp: int = 1) -> dict:
        import mitsuba as mi

        if abs(self.focal_y_ratio - 1.0) > 1e-9:
            raise ValueError(f"camera {self.name}: Mitsuba's perspective sensor has one focal length (fy / fx = "
                             f"{self.focal_y_ratio:g})")
        ox, oy = self.principal_offset()
        return {
            "principal_point_offset_x": float(ox),
            "principal_point_offset_y": float(oy),
            "type": "perspective",
            "fov": float(self.fov_x_deg),
            "fov_axis": "x",
            "near_clip": 1e-3,
            "far_clip": 1e4,
            "to_world": mi.ScalarTransform4f(self.to_world.tolist()),
            "film": {
                "type": "hdrfilm",
                "width": int(self.width),
                "height": int(self.height),
                "rfilter": {"type": "box"},
                "pixel_format": "rgba",
            },
            "sampler": {"type": "independent", "sample_count": int(spp)},
        }


def principal_xml(camera: Camera, indent: str) -> str:
    """The perspective sensor's principal point offsets as Mitsuba XML lines ("" when centred)."""
    if camera.principal is None:
        return ""
    ox, oy = camera.principal_offset()
    return (f'{indent}<float name="principal_point_offset_x" value="{ox:.9g}"/>\n'
            f'{indent}<float name="principal_point_offset_y" value="{oy:.9g}"/>\n')


def camera_from_intrinsics(name: str, to_world: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                           width: int, height: int) -> Camera:
    """A Camera from pixel intrinsics (pixel centres at +0.5)."""
    fov_x = math.degrees(2.0 * math.atan(0.5 * width / fx))
    centred = abs(cx - 0.5 * width) < 1e-9 and abs(cy - 0.5 * height) < 1e-9
    return Camera(name, np.asarray(to_world, np.float64), fov_x, int(width), int(height), focal_y_ratio=fy / fx,
                  principal=None if centred else (float(cx), float(cy)))


def nerf_to_camera(name: str, transform_matrix, camera_angle_x: float, width: int, height: int) -> Camera:
    """A NeRF-synthetic frame (camera-to-world in OpenGL axes, radians) as a Mitsuba camera."""
    c2w = np.asarray(transform_matrix, dtype=np.float64).reshape(4, 4)
    return Camera(name, c2w @ OPENGL_TO_MITSUBA, math.degrees(camera_angle_x), int(width), int(height))


def camera_to_nerf(camera: Camera) -> tuple[np.ndarray, float]:
    """Inverse of nerf_to_camera: (transform_matrix, camera_angle_x in radians)."""
    return camera.to_world @ OPENGL_TO_MITSUBA, math.radians(camera.fov_x_deg)


def look_at(origin, target, up) -> np.ndarray:
    """Mitsuba camera-to-world (4, 4) looking from origin at target (same as mi's look_at)."""
    origin, target, up = (np.asarray(v, dtype=np.float64) for v in (origin, target, up))
    d = target - origin
    d /= np.linalg.norm(d)
    left = np.cross(up, d)
    left /= np.linalg.norm(left)
    new_up = np.cross(d, left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, new_up, d, origin
    return m


def pixel_jitter(n_pixels: int, index: int, count: int, rng: np.random.Generator) -> np.ndarray:
    """Offsets in [0, 1)^2 for the `index`-th of `count` primary rays of each pixel: one random
    point in cell `index` of a sqrt(count) x sqrt(count) grid (stratified; random if not square)."""
    side = int(round(count ** 0.5))
    if side * side != count:
        return rng.random((n_pixels, 2))
    cell = np.array([index % side, index // side], dtype=np.float64)
    return (cell + rng.random((n_pixels, 2))) / side


def camera_rays(camera: Camera, jitter: np.ndarray | None = None,
                pixels: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """World-space rays through pixels (row-major, y down): every pixel, or the flat pixel indices
    `pixels` (N,). jitter: (number of rays, 2) offsets in [0,1)."""
    h, w = camera.height, camera.width
    if pixels is None:
        ys, xs = np.meshgrid(np.arange(h, dtype=np.float64), np.arange(w, dtype=np.float64), indexing="ij")
    else:
        ys, xs = np.divmod(np.asarray(pixels, dtype=np.int64), w)
        ys, xs = ys.astype(np.float64), xs.astype(np.float64)
    if jitter is None:
        px, py = xs.ravel() + 0.5, ys.ravel() + 0.5
    else:
        px, py = xs.ravel() + jitter[:, 0], ys.ravel() + jitter[:, 1]
    fx, fy, cx, cy = camera.intrinsics()
    # Inverse of Camera.project: +X is left in Mitsuba camera space.
    local = np.stack([(cx - px) / fx, (cy - py) / fy, np.ones_like(px)], -1)
    d = local @ camera.to_world[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    o = np.broadcast_to(camera.origin, d.shape)
    return np.ascontiguousarray(o, dtype=np.float32), np.ascontiguousarray(d, dtype=np.float32)


def world_rotation(src: str, dst: str) -> np.ndarray:
    """The (3, 3) rotation taking world `src` to world `dst` ("mitsuba" Y-up / "blender" Z-up)."""
    if src == dst:
        return np.eye(3)
    return MITSUBA_TO_BLENDER if (src, dst) == ("mitsuba", "blender") else MITSUBA_TO_BLENDER.T


def convert_world(camera: Camera, src: str, dst: str) -> Camera:
    """Express a camera given in world `src` in world `dst`."""
    if src == dst:
        return camera
    rot = np.eye(4)
    rot[:3, :3] = world_rotation(src, dst)
    return replace(camera, to_world=rot @ camera.to_world)
