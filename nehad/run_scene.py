"""A training run as a runtime scene (runtime/scene.py): the adapter that lets every command
draw a run folder with its torch model. The runtime never imports it; the command line names it
(``nehad.run_scene:open_run``) among the scene openers it passes to ``open_scene``."""

from __future__ import annotations

from pathlib import Path

from nehad.runtime.scene import Scene, SceneError, file_sha256


class RunScene(Scene):
    """RUN/model.pt: the deformed Gaussians at any time, computed by the torch model; the
    background the run was trained with; its dataset's test cameras (when the dataset is still
    there), the first of them the default camera."""

    kind = "run"

    def __init__(self, path, lod: int | None = None):
        super().__init__(path)
        from nehad.model import load_run  # torch: only for this scene kind

        self.model, self.info = load_run(self.path)
        self.default_background = self.info.background
        self.time_range = self.info.time_range
        self.sh_degree = self.info.degree_for(self.model)
        self.lod = lod
        self._keep = None
        total = len(self.model.gaussians)
        self.num_gaussians = total
        if lod is not None:
            count = self.num_layers
            if not 0 <= lod < count:
                raise SceneError(f"{{lod}} {lod}: run {self.path} has {count} layer(s), "
                                 f"0..{count - 1}", "lod")
            self._keep = self._layers() <= lod
            self.num_gaussians = int(self._keep.sum())
        means = self.model.gaussians.means.detach().cpu().numpy()
        if len(means):
            import numpy as np

            self.aabb = np.stack([means.min(0), means.max(0)])
        first = dataset_test_cameras(self.info.data_dir, ":0")  # one frame: no work for the whole split here
        self.default_camera = first[0] if first else None

    def _layers(self):
        from nehad.lod import run_layers

        return run_layers(self.info, len(self.model.gaussians))

    @property
    def num_layers(self) -> int:
        layers = self._layers()
        return int(layers.max()) + 1 if len(layers) else 1

    def cameras(self) -> list:
        return dataset_test_cameras(self.info.data_dir)

    def gaussians(self, time=None):
        from nehad.model import cloud_at

        cloud = cloud_at(self.model, self.middle_time() if time is None else time,
                         self.sh_degree)
        if self._keep is not None:
            from nehad.runtime.gaussians import GaussianCloud

            k = self._keep
            cloud = GaussianCloud(cloud.means[k], cloud.scales[k], cloud.quats[k],
                                  cloud.opacities[k], cloud.sh[k])
        return cloud

    def describe(self) -> str:
        total = len(self.model.gaussians)
        if self._keep is not None:
            return (f"run {self.path.name}: layers 0..{self.lod}, {self.num_gaussians} of "
                    f"{total} Gaussians, SH degree {self.sh_degree}")
        return f"run {self.path.name}: {total} Gaussians, SH degree {self.sh_degree}"

    def digest(self) -> str:
        return file_sha256(self.path / "model.pt")


def dataset_test_cameras(data_dir: str | None, frame: str = "") -> list:
    """The cameras of the run's dataset's test split, or of its frame `frame` (":0"); [] when
    the dataset is gone or unreadable."""
    test = Path(data_dir or "") / "transforms_test.json"
    if not test.is_file():
        return []
    from nehad.runtime.cameras import CameraError, load_view

    try:
        cams = load_view(f"{test}{frame}")
    except CameraError:
        return []
    return cams if isinstance(cams, list) else [cams]


def open_run(path, lod: int | None = None, threads: int | None = None):
    """The scene opener of a training run folder (RUN/model.pt), else None."""
    p = Path(path)
    if not (p.is_dir() and (p / "model.pt").is_file()):
        return None
    return RunScene(p, lod=lod)


__all__ = ["RunScene", "open_run"]
