"""Pinhole cameras in the conventions of SPEC section 3.

A :class:`Camera` always stores the world-to-camera transform in OpenCV axes (x right, y down,
z forward). Pixel (i, j) has its centre at (i + 0.5, j + 0.5); a camera-space point (X, Y, Z)
projects to u = fx X/Z + cx, v = fy Y/Z + cy.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# Blender/NeRF/D-NeRF store camera-to-world with OpenGL axes (y up, z back); negating the
# rotation's columns 1 and 2 turns it into OpenCV axes (SPEC section 3).
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


class CameraError(ValueError):
    """A camera description is missing a field or holds an invalid value (names the field)."""


@dataclass(frozen=True)
class Camera:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    world_to_camera: np.ndarray = field(repr=False)  # (4, 4) float64, OpenCV axes
    time: float | None = None
    name: str = ""

    @classmethod
    def from_camera_to_world(cls, camera_to_world, width, height, fx, fy, cx=None, cy=None,
                             convention="opengl", time=None, name=""):
        c2w = np.asarray(camera_to_world, dtype=np.float64)
        if convention == "opengl":
            c2w = c2w @ _GL_TO_CV
        elif convention != "opencv":
            raise CameraError(f"convention: expected 'opengl' or 'opencv', got {convention!r}")
        w2c = np.linalg.inv(c2w)
        return cls(int(width), int(height), float(fx), float(fy),
                   float(width) / 2 if cx is None else float(cx),
                   float(height) / 2 if cy is None else float(cy), w2c, time, name)

    @property
    def camera_to_world(self) -> np.ndarray:
        """Camera-to-world in OpenCV axes."""
        return np.linalg.inv(self.world_to_camera)

    @property
    def centre(self) -> np.ndarray:
        """Camera centre in world coordinates."""
        r = self.world_to_camera[:3, :3]
        return -r.T @ self.world_to_camera[:3, 3]

    @property
    def fov_x(self) -> float:
        return float(2 * np.arctan(self.width / (2 * self.fx)))

    @property
    def fov_y(self) -> float:
        return float(2 * np.arctan(self.height / (2 * self.fy)))

    def scaled(self, factor: float) -> "Camera":
        """The same camera for an image resized by `factor` (e.g. 0.5 for half resolution)."""
        w = int(round(self.width * factor))
        h = int(round(self.height * factor))
        sx, sy = w / self.width, h / self.height
        return Camera(w, h, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy,
                      self.world_to_camera, self.time, self.name)

    def with_size(self, width: int, height: int) -> "Camera":
        """The same field of view rendered at another image size."""
        return self.scaled(1.0) if (width, height) == (self.width, self.height) else Camera(
            int(width), int(height), self.fx * width / self.width, self.fy * height / self.height,
            self.cx * width / self.width, self.cy * height / self.height,
            self.world_to_camera, self.time, self.name)
