"""Issue 15: bad inputs and kills, as a new user meets them. Every case asserts the exit code, the
one-line message and that nothing is left in the output location.

1. no traceback: corrupt/truncated/empty checkpoints and models, binary config and jobs files,
   the torch-free install;
2. start-up validation before anything is written (train, demo, --resume);
3. the memory bound (render, video, batch, ply, the rasterizer's tile lists);
4. temporary files name their writer; stale ones are removed by the rerun (SIGKILL tests);
5. one writer per output (video, train);
6. the exported file's digest, checked on every load;
7. index out of range, --time with a static PLY, metrics.jsonl after resume, Ctrl-C on train.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from nehad.cli.main import main
from nehad.runtime import tempfiles
from nehad.runtime.images import atomic_path

import stacks
from clean_errors import one_error as _one_error
from torch_blocker import blocked_torch_env
from video_model import build_tiny_export

pytestmark = pytest.mark.slow
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    """(model.onnx, scene, run): the shared tiny exported model and its training run."""
    onnx_path, scene = build_tiny_export(tmp_path_factory)
    return onnx_path, scene, onnx_path.parent / "run"


@pytest.fixture(scope="module")
def static_ply(tmp_path_factory):
    """A static 3DGS PLY of the synthetic scene (300 Gaussians)."""
    from nehad.data.synth_gaussians import scene_gaussians
    from nehad.runtime.ply import write_gaussian_ply

    return write_gaussian_ply(tmp_path_factory.mktemp("ply") / "gaussians.ply",
                              scene_gaussians("spheres", 0.5, 300))


def _invoke(args, **kw):
    return CliRunner().invoke(main, [str(a) for a in args], **kw)


def _run_cli(args, env=None, timeout=300, **kw):
    return stacks.run([sys.executable, "-m", "nehad.cli.main", *map(str, args)],
                      timeout=timeout, env=env or ENV, **kw)


def _proc_error(proc, *needles) -> str:
    assert proc.returncode == 1, (proc.returncode, proc.stdout, proc.stderr)
    assert "Traceback" not in proc.stderr, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("Error: "), proc.stderr
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


def _listing(folder: Path) -> list[str]:
    return sorted(p.name for p in Path(folder).iterdir())


def _dead_pid() -> int:
    proc = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True)
    return int(proc.stdout)


# ---------------------------------------------------------------------------------------------
# 1. no traceback for any user input


def _bad_model_pt(kind: str, good: Path, dest: Path) -> None:
    data = good.read_bytes()
    if kind == "random":
        dest.write_bytes(os.urandom(5000))
    elif kind == "truncated":
        dest.write_bytes(data[:len(data) // 3])
    elif kind == "empty":
        dest.write_bytes(b"")
    elif kind == "flipped":  # 4 bytes inside a tensor record: only the zip CRC tells
        with zipfile.ZipFile(good) as z:
            big = max(z.infolist(), key=lambda i: i.file_size)
            start = big.header_offset + 30 + len(big.filename.encode()) + len(big.extra) + 64
        b = bytearray(data)
        for k in range(4):
            b[start + k] ^= 0xFF
        dest.write_bytes(bytes(b))
    elif kind == "code":  # a pickle that would run code: weights_only refuses it
        import torch

        torch.save({"gaussians": {}, "field": {}, "config": _Evil()}, dest)
    elif kind == "foreign":
        import torch

        torch.save([1, 2, 3], dest)
    elif kind in _EDITS:  # an intact archive whose values are not a run's (hand-edited)
        import torch

        state = torch.load(good, map_location="cpu", weights_only=True)
        _EDITS[kind](state)
        torch.save(state, dest)


def _nan_field(state):
    key = next(k for k, v in state["field"].items() if v.is_floating_point() and v.numel())
    state["field"][key] = state["field"][key] * float("nan")


def _quats_cut(state):
    state["gaussians"]["quats"] = state["gaussians"]["quats"][:10]


def _no_gaussians(state):
    state["gaussians"] = {k: v[:0] for k, v in state["gaussians"].items()}


def _zero_quat(state):
    state["gaussians"]["quats"][5] = 0.0


_EDITS = {"nan_field": _nan_field,
          "background_word": lambda state: state.update(background="white"),
          "sh_degree_9": lambda state: state.update(sh_degree=9),
          "time_range_nan": lambda state: state.update(time_range=[float("nan"), 1.0]),
          "quats_cut": _quats_cut, "no_gaussians": _no_gaussians, "zero_quat": _zero_quat,
          "format_9": lambda state: state.update(format="nehad-run/9"),
          "extent_negative": lambda state: state.update(extent=-1.0)}


class _Evil:
    def __reduce__(self):
        return (os.system, ("echo pwned",))


BAD_MODELS = ("random", "truncated", "empty", "flipped", "code", "foreign", "nan_field",
              "background_word", "sh_degree_9", "time_range_nan", "quats_cut", "no_gaussians",
              "zero_quat", "format_9", "extent_negative")


@pytest.fixture(scope="module")
def bad_runs(model, tmp_path_factory):
    _, _, run = model
    root = tmp_path_factory.mktemp("bad_runs")
    out = {}
    for kind in BAD_MODELS:
        d = root / kind
        d.mkdir()
        shutil.copy(run / "config.yaml", d / "config.yaml")
        _bad_model_pt(kind, run / "model.pt", d / "model.pt")
        out[kind] = d
    return out


@pytest.mark.parametrize("kind", BAD_MODELS)
@pytest.mark.parametrize("command", ["render", "export", "eval", "ply"])
def test_damaged_model_pt_is_one_error_line(bad_runs, model, tmp_path, kind, command):
    _, scene, _ = model
    run = bad_runs[kind]
    out = tmp_path / "out"
    out.mkdir()
    args = {"render": ["render", run, "--view", f"{scene}/transforms_test.json:0", "--time",
                       "0.5", "-o", out / "x.png"],
            "export": ["export", run, "-o", out / "x.onnx"],
            "eval": ["eval", run, "--no-lpips", "--quiet"],
            "ply": ["ply", run, "--time", "0.5", "-o", out / "x.ply"]}[command]
    before = _listing(run)
    line = _one_error(_invoke(args), f"{run}/model.pt")
    want = {"random": "truncated or corrupt", "truncated": "truncated or corrupt",
            "empty": "empty", "flipped": "checksum", "code": "refused",
            "foreign": "not a nehad run file", "nan_field": "NaN or infinite",
            "background_word": "background", "sh_degree_9": "sh_degree",
            "time_range_nan": "time_range", "quats_cut": "different numbers of rows",
            "no_gaussians": "holds no Gaussians", "zero_quat": "quats are all zero",
            "format_9": "format", "extent_negative": "extent"}[kind]
    assert want in line
    assert _listing(out) == [] and _listing(run) == before


@pytest.mark.parametrize("split", ["train", "test"])
def test_a_split_without_frames_is_one_error_line(model, tmp_path, split):
    """A transforms file whose frames list is empty: train (the train split) and eval (the
    test split) name the split instead of failing inside numpy."""
    _, scene, run = model
    data = tmp_path / "scene"
    shutil.copytree(scene, data)
    doc = json.loads((data / f"transforms_{split}.json").read_text())
    doc["frames"] = []
    (data / f"transforms_{split}.json").write_text(json.dumps(doc))
    if split == "train":
        res = _invoke(["train", data, "-o", tmp_path / "run", "--preset", "test"])
    else:
        res = _invoke(["eval", run, "--no-lpips", "--quiet", "--data", data])
    _one_error(res, f"the {split} split has no frames")
    assert not (tmp_path / "run").exists()


def test_synth_refuses_a_folder_that_holds_files(tmp_path):
    """Writing a scene over another would leave the old one's images beside the new ones."""
    out = tmp_path / "scene"
    out.mkdir()
    (out / "r_001.png").write_bytes(b"old")
    res = _invoke(["synth", out, "--resolution", "16", "--frames", "2", "--gaussians", "0"])
    assert res.exit_code == 2 and "is not empty" in res.output, res.output
    assert _listing(out) == ["r_001.png"]


@pytest.mark.parametrize("content", [os.urandom(300) + b"\xff", b"\xff\xfe\x00a: 1\n",
                                     b"a: 1\n\x00\x01binary"])
def test_binary_config_and_jobs_files(model, tmp_path, content):
    _, scene, _ = model
    cfg = tmp_path / "bad.yaml"
    cfg.write_bytes(content)
    _one_error(_invoke(["train", scene, "-o", tmp_path / "run", "--preset", "test",
                        "--config", cfg]), str(cfg))
    _one_error(_invoke(["batch", cfg, "--check"]), str(cfg))
    assert _listing(tmp_path) == ["bad.yaml"]


TORCH_COMMANDS = {
    "export": lambda run, scene, out: ["export", run, "-o", out / "m.onnx"],
    "render": lambda run, scene, out: ["render", run, "--view", f"{scene}/transforms_test.json:0",
                                       "--time", "0.5", "-o", out / "x.png"],
    "train": lambda run, scene, out: ["train", scene, "-o", out / "run", "--preset", "test"],
    "eval": lambda run, scene, out: ["eval", run, "--no-lpips"],
    "demo": lambda run, scene, out: ["demo", "-o", out / "demo"],
}


@pytest.mark.parametrize("command", sorted(TORCH_COMMANDS))
def test_torch_free_install_names_the_extra(model, tmp_path, command):
    """tests/torch_blocker.py: `import torch` fails inside the package (a blocked or broken
    install)."""
    _, scene, run = model
    out = tmp_path / "out"
    out.mkdir()
    before = _listing(run)
    proc = _run_cli(TORCH_COMMANDS[command](run, scene, out),
                    env={**blocked_torch_env(tmp_path), "OMP_NUM_THREADS": "1",
                         "NUMBA_NUM_THREADS": "1"})
    _proc_error(proc, f"Error: nehad {command} needs torch", "pip install -e '.[train]'")
    assert _listing(out) == [] and _listing(run) == before


def test_torch_not_installed_names_the_extra(model, tmp_path):
    """The real torch-free install: `import torch` raises ModuleNotFoundError."""
    _, _, run = model
    code = ("import sys; sys.modules['torch'] = None\n"
            "from nehad.cli.main import main\n"
            f"main(['export', {str(run)!r}, '-o', {str(tmp_path / 'm.onnx')!r}], "
            f"prog_name='nehad')")
    proc = subprocess.run([sys.executable, "-c", code], env=ENV, capture_output=True, text=True,
                          timeout=300)
    _proc_error(proc, "Error: nehad export needs torch", "pip install -e '.[train]' torch==2.13.0")
    assert _listing(tmp_path) == []


def test_missing_extra_recognises_only_the_training_packages():
    from nehad.cli.errors import missing_extra

    assert missing_extra(ModuleNotFoundError("No module named 'torch'", name="torch")) == "torch"
    assert missing_extra(ModuleNotFoundError("No module named 'onnx.checker'",
                                             name="onnx.checker")) == "onnx"
    assert missing_extra(ModuleNotFoundError("No module named 'foo'", name="foo")) is None
    assert missing_extra(ImportError("cannot import name 'x' from 'nehad'")) is None


# ---------------------------------------------------------------------------------------------
# 2. start-up validation before anything is written


def _broken(scene: Path, dest: Path, how: str) -> Path:
    shutil.copytree(scene, dest)
    if how == "missing image":
        (dest / "train" / "r_001.png").unlink()
    elif how == "non-JSON transforms":
        (dest / "transforms_train.json").write_text("{not json")
    elif how == "NaN pose":
        doc = json.loads((dest / "transforms_train.json").read_text())
        doc["frames"][0]["transform_matrix"][0][3] = float("nan")
        (dest / "transforms_train.json").write_text(json.dumps(doc))
    elif how == "corrupt PNG":
        (dest / "train" / "r_002.png").write_bytes(os.urandom(100))
    return dest


@pytest.mark.parametrize("how", ["missing image", "non-JSON transforms", "NaN pose",
                                 "corrupt PNG"])
def test_train_on_broken_dataset_writes_nothing(model, tmp_path, how):
    _, scene, _ = model
    data = _broken(scene, tmp_path / "data", how)
    _one_error(_invoke(["train", data, "-o", tmp_path / "run", "--preset", "test", "--quiet"]),
               str(data))
    assert not (tmp_path / "run").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_train_after_fixing_the_dataset_is_not_refused(model, tmp_path):
    _, scene, _ = model
    data = _broken(scene, tmp_path / "data", "missing image")
    args = ["train", data, "-o", tmp_path / "run", "--preset", "test", "--quiet",
            "--set", "coarse.iterations=4", "--set", "fine.iterations=4"]
    _one_error(_invoke(args), "r_001.png")
    shutil.copy(scene / "train" / "r_001.png", data / "train" / "r_001.png")
    res = _invoke(args)
    assert res.exit_code == 0, res.output
    assert (tmp_path / "run" / "model.pt").is_file()


def test_resume_of_a_missing_run_is_an_error(model, tmp_path):
    _, scene, _ = model
    _one_error(_invoke(["train", scene, "-o", tmp_path / "nope", "--preset", "test", "--resume"]),
               "no run to resume", "nope")
    assert _listing(tmp_path) == []


def test_a_run_is_not_written_into_its_dataset(model, tmp_path):
    """`train DATA -o DATA` mixed model.pt, checkpoints/ and config.yaml into the dataset."""
    _, scene, _ = model
    data = tmp_path / "data"
    shutil.copytree(scene, data)
    before = _listing(data)
    _one_error(_invoke(["train", data, "-o", data / ".", "--preset", "test"]),
               "that is the dataset folder")
    assert _listing(data) == before


def test_demo_checks_its_settings_before_writing(tmp_path):
    _one_error(_invoke(["demo", "-o", tmp_path / "demo", "--set", "bogus.key=1"]), "bogus")
    _one_error(_invoke(["demo", "-o", tmp_path / "demo", "--set", "fine.iterations=abc"]),
               "fine.iterations")
    assert _listing(tmp_path) == []


# ---------------------------------------------------------------------------------------------
# 3. memory bound


@pytest.fixture
def cap_16g(monkeypatch):
    """Make the limit the same on every machine: 16 GB."""
    monkeypatch.setenv("NEHAD_MAX_FRAME_MEMORY", "16G")


def test_render_video_batch_ply_refuse_what_does_not_fit(model, static_ply, tmp_path, cap_16g):
    onnx_path, scene, _ = model
    out = tmp_path / "out"
    out.mkdir()
    start = time.perf_counter()
    _one_error(_invoke(["render", onnx_path, "--view", f"{scene}/transforms_test.json:0",
                        "--time", "0.5", "--size", "32768x32768", "-o", out / "big.png"]),
               "--size 32768x32768", "GB of memory", "NEHAD_MAX_FRAME_MEMORY=16G")
    _one_error(_invoke(["render", static_ply, "--view",
                        f"{scene}/transforms_test.json:0", "--size", "32768x32768",
                        "-o", out / "big.png"]), "--size 32768x32768")
    _one_error(_invoke(["video", onnx_path, "-o", out / "big.mp4", "--size", "32768x32768",
                        "--frames", "2"]), "--size 32768x32768", "memory")
    jobs = out / "jobs.yaml"
    jobs.write_text(textwrap.dedent(f"""\
        jobs:
          - {{name: big, model: {onnx_path}, output: big.mp4, frames: 2, size: 32768x32768}}
          - {{name: still, model: {onnx_path}, output: big.png, time: 0.5, size: 32768x32768}}
        """))
    res = _invoke(["batch", jobs, "--quiet", "--workers", "1"])
    assert res.exit_code == 1 and isinstance(res.exception, (SystemExit, type(None)))
    assert res.output.count("size 32768x32768: a 32768x32768 frame") == 2, res.output
    assert time.perf_counter() - start < 60  # refused up front, not after paging for minutes
    assert _listing(out) == ["jobs.yaml"]


def test_ply_and_pool_limits(model, tmp_path, monkeypatch):
    onnx_path, _, _ = model
    monkeypatch.setenv("NEHAD_MAX_FRAME_MEMORY", "100k")
    _one_error(_invoke(["ply", onnx_path, "--time", "0.5", "-o", tmp_path / "f.ply"]),
               "Gaussians need about")
    # a 256x256 frame needs about 6 MB: one fits under 10 MB, two workers' frames at once do not
    monkeypatch.setenv("NEHAD_MAX_FRAME_MEMORY", "10M")
    _one_error(_invoke(["video", onnx_path, "-o", tmp_path / "v.mp4", "--size", "256x256",
                        "--frames", "4", "--workers", "2"]), "2 256x256 frames", "fewer workers")
    assert _listing(tmp_path) == []
    monkeypatch.setenv("NEHAD_MAX_FRAME_MEMORY", "lots")
    _one_error(_invoke(["render", onnx_path, "--time", "0.5", "--view",
                        f"{onnx_path.parent}/scene/transforms_test.json:0", "-o",
                        tmp_path / "x.png"]), "NEHAD_MAX_FRAME_MEMORY='lots'")
    assert _listing(tmp_path) == []


def test_tile_lists_are_checked_before_they_are_allocated(monkeypatch):
    import numpy as np

    from nehad.runtime.cameras import Camera
    from nehad.runtime.gaussians import GaussianCloud
    from nehad.runtime.memory import FrameMemoryError
    from nehad.runtime.raster import render

    n = 400  # big Gaussians in front of the camera: each covers the whole 512x512 frame
    cloud = GaussianCloud(np.zeros((n, 3)) + [0, 0, 3], np.full((n, 3), 2.0),
                          np.tile([1.0, 0, 0, 0], (n, 1)), np.full(n, 0.9), np.zeros((n, 1, 3)))
    cam = Camera(512, 512, 400.0, 400.0, 256.0, 256.0, np.eye(4))
    assert render(cloud, cam).alpha.mean() > 0.9
    monkeypatch.setenv("NEHAD_MAX_FRAME_MEMORY", "1M")  # 400 x 1024 tiles x 4 bytes = 1.6 MB
    with pytest.raises(FrameMemoryError, match=r"tile lists need about .*\(409600 Gaussian-tile"):
        render(cloud, cam)


def test_available_memory_is_read_and_used(monkeypatch):
    from nehad.runtime import memory

    avail = memory.available_memory()
    if sys.platform.startswith("linux"):
        assert avail is not None and avail > 1 << 20
    monkeypatch.delenv("NEHAD_MAX_FRAME_MEMORY", raising=False)
    monkeypatch.setattr(memory, "available_memory", lambda: 24 * 10**9)
    with pytest.raises(memory.FrameMemoryError, match=r"memory available \(24.0 GB\)"):
        memory.check_frame_memory(32768, 32768, 1000, "--size 32768x32768")
    memory.check_frame_memory(4096, 4096, 10**6, "--size 4096x4096")  # 1.7 GB: fits


# ---------------------------------------------------------------------------------------------
# 4. temporary files


def test_temp_names_say_who_wrote_them_and_stale_ones_go(tmp_path):
    target = tmp_path / "model.onnx"
    with atomic_path(target) as tmp:
        name = Path(tmp).name
        assert name.startswith(f".model.nehad-{os.getpid()}-") and name.endswith(".tmp.onnx")
        Path(tmp).write_bytes(b"x")
    host = tempfiles._host()
    dead = _dead_pid()
    old = time.time() - 2 * tempfiles.STALE_SECONDS
    files = {
        "stale": f".model.nehad-{dead}-{host}-abc12345.tmp.onnx",  # this host, writer gone
        "live": f".model.nehad-{os.getppid()}-{host}-abc12345.tmp.onnx",  # writer running
        "other_new": ".model.nehad-12-otherhost-abc12345.tmp.onnx",  # recent, other machine
        "other_old": ".model.nehad-13-otherhost-abc12346.tmp.onnx",  # abandoned, other machine
        "legacy_old": ".model.k3j4h5g6.tmp.onnx",  # before issue 15, an hour old
        "legacy_new": ".model.k3j4h5g7.tmp.onnx",  # before issue 15, recent
        "other_target": f".other.nehad-{dead}-{host}-abc12345.tmp.onnx",
        "unrelated": ".model.onnx.keep",
    }
    for key, fname in files.items():
        (tmp_path / fname).write_bytes(b"partial")
        if key in ("other_old", "legacy_old"):
            os.utime(tmp_path / fname, (old, old))
    with atomic_path(target) as tmp:
        Path(tmp).write_bytes(b"y")
    left = set(_listing(tmp_path))
    for key in ("stale", "other_old", "legacy_old"):
        assert files[key] not in left, key
    for key in ("live", "other_new", "legacy_new", "other_target", "unrelated"):
        assert files[key] in left, key
    assert target.read_bytes() == b"y"


HANG_ON_REPLACE = stacks.DUMP_ON_USR1 + """
import os, sys, time
real = os.replace
def hang(src, dst, *a, **k):
    if str(dst).endswith(sys.argv[1]):
        open(sys.argv[2], "w").close()
        time.sleep(600)
    return real(src, dst, *a, **k)
os.replace = hang
from nehad.cli.main import main
main(sys.argv[3:], prog_name="nehad")
"""


def _wait_for_flag(proc, flag, timeout: float = 300.0) -> None:
    """Wait until `proc` creates `flag`; fail (with its stderr) if it exits or times out first."""
    deadline = time.time() + timeout
    while not flag.exists():
        assert proc.poll() is None, proc.stderr.read()
        if time.time() > deadline:
            stacks.kill_with_stacks(proc, f"no {flag.name} after {timeout:g} s")
        time.sleep(0.1)


def _kill_while_writing(tmp_path, suffix: str, args) -> None:
    """Run the CLI with `args` in a process that stops just before renaming its `suffix` temp
    file into place, and SIGKILL it there (the moment a kill leaves a temp file behind)."""
    flag = tmp_path / "ready.flag"
    proc = subprocess.Popen([sys.executable, "-c", HANG_ON_REPLACE, suffix, str(flag),
                             *map(str, args)], env=ENV, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    try:
        _wait_for_flag(proc, flag)
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    flag.unlink()


def _temps(folder: Path) -> list[str]:
    return [p.name for p in folder.iterdir() if ".tmp" in p.name and p.name.startswith(".")]


def test_sigkill_during_export_then_rerun_leaves_no_temp(model, tmp_path):
    _, _, run = model
    out = tmp_path / "out"
    out.mkdir()
    _kill_while_writing(tmp_path, ".onnx", ["export", run, "-o", out / "model.onnx"])
    left = _temps(out)
    assert len(left) == 1 and left[0].startswith(".model.nehad-"), _listing(out)
    assert not (out / "model.onnx").exists()
    res = _invoke(["export", run, "-o", out / "model.onnx"])
    assert res.exit_code == 0, res.output
    assert _listing(out) == ["model.onnx"]


def test_sigkill_during_encoding_then_rerun_leaves_no_temp(model, tmp_path):
    onnx_path, _, _ = model
    out = tmp_path / "out"
    out.mkdir()
    args = ["video", onnx_path, "-o", out / "orbit.mp4", "--frames", "4", "--workers", "1",
            "--quiet"]
    _kill_while_writing(tmp_path, ".mp4", args)
    left = _temps(out)
    assert len(left) == 1 and left[0].startswith(".orbit.nehad-") and left[0].endswith(".tmp.mp4")
    assert (out / "orbit.mp4.frames").is_dir()  # the frames were rendered before the encoding
    res = _invoke([*args, "--resume"])
    assert res.exit_code == 0, res.output
    assert "4 already there kept" in res.output
    assert _listing(out) == ["orbit.mp4"]


def test_resume_removes_a_killed_checkpoint_write(model, tmp_path):
    _, scene, _ = model
    run = tmp_path / "run"
    args = ["train", scene, "-o", run, "--preset", "test", "--quiet", "--set",
            "coarse.iterations=4", "--set", "fine.iterations=4"]
    assert _invoke(args).exit_code == 0
    ck = run / "checkpoints"
    stale = ck / f".step_0000006.nehad-{_dead_pid()}-{tempfiles._host()}-abcd1234.tmp.pt"
    legacy = ck / ".step_0000006.pt.abcd1234"
    for p in (stale, legacy):
        p.write_bytes(b"partial")
    old = time.time() - 2 * tempfiles.STALE_SECONDS
    os.utime(legacy, (old, old))
    res = _invoke([*args, "--resume"])
    assert res.exit_code == 0, res.output
    assert not stale.exists() and not legacy.exists()
    assert not _temps(run) and not _temps(ck)


# ---------------------------------------------------------------------------------------------
# 5. one writer per output


HANG_AFTER_FIRST_FRAME = stacks.DUMP_ON_USR1 + """
import sys, time
import nehad.runtime.distribute as d
real = d.render_frame_task
def slow(task):
    r = real(task)
    open(sys.argv[1], "w").close()
    time.sleep(600)
    return r
d.render_frame_task = slow
from nehad.cli.main import main
main(sys.argv[2:], prog_name="nehad")
"""


def test_second_video_with_the_same_output_refuses(model, tmp_path):
    onnx_path, _, _ = model
    out = tmp_path / "orbit.mp4"
    args = ["video", onnx_path, "-o", out, "--frames", "4", "--workers", "1", "--quiet"]
    flag = tmp_path / "ready.flag"
    first = subprocess.Popen([sys.executable, "-c", HANG_AFTER_FIRST_FRAME, str(flag),
                              *map(str, args)], env=ENV, stdout=subprocess.DEVNULL,
                             stderr=subprocess.PIPE, text=True)
    try:
        _wait_for_flag(first, flag)
        frames = tmp_path / "orbit.mp4.frames"
        held = _listing(frames)
        assert "frame_00000.png" in held
        line = _one_error(_invoke(args), str(out), f"pid {first.pid}", "is writing it")
        assert "nehad video" in line
        assert _listing(frames) == held  # the first run's folder is untouched
        # another output sharing the frame folder is refused too
        _one_error(_invoke(["video", onnx_path, "-o", tmp_path / "other.mp4", "--frames-dir",
                            frames, "--frames", "4", "--workers", "1"]), "is writing it")
        first.send_signal(signal.SIGKILL)  # the kernel drops the lock with the process
        first.wait(30)
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
    res = _invoke([*args, "--resume"])
    assert res.exit_code == 0, res.output
    assert _listing(tmp_path) == ["orbit.mp4", "ready.flag"]


def test_second_train_into_the_same_run_refuses(model, tmp_path):
    from nehad.runtime.lock import output_lock

    _, scene, _ = model
    run = tmp_path / "run"
    with output_lock(run, "nehad train"):
        _one_error(_invoke(["train", scene, "-o", run, "--preset", "test", "--quiet"]),
                   f"{run}: nehad train (pid {os.getpid()}", "is writing it")
    assert not run.exists() and _listing(tmp_path) == []


# ---------------------------------------------------------------------------------------------
# 6. integrity of the exported file


def _flip_weights(src: Path, dest: Path) -> None:
    from nehad.runtime.onnx_proto import summarize

    data = bytearray(src.read_bytes())
    start, end = summarize(bytes(data)).graph_spans[0]
    mid = (start + end) // 2
    for k in range(4):
        data[mid + k] ^= 0x55
    dest.write_bytes(bytes(data))


def test_damaged_onnx_is_refused_by_every_load(model, tmp_path):
    onnx_path, scene, _ = model
    res = _invoke(["info", onnx_path])
    assert res.exit_code == 0 and "integrity:    graph sha256" in res.output
    bad = tmp_path / "bad.onnx"
    _flip_weights(onnx_path, bad)
    out = tmp_path / "out"
    out.mkdir()
    view = f"{scene}/transforms_test.json:0"
    for args in (["info", bad],
                 ["render", bad, "--view", view, "--time", "0.5", "-o", out / "x.png"],
                 ["video", bad, "-o", out / "x.mp4", "--frames", "2"],
                 ["ply", bad, "--time", "0.5", "-o", out / "x.ply"]):
        _one_error(_invoke(args), str(bad), "damaged", "graph_sha256")
    assert _listing(out) == []
    from nehad.runtime.onnx_model import OnnxModel, OnnxModelError

    with pytest.raises(OnnxModelError, match="damaged"):
        OnnxModel(bad)


def test_model_without_digest_still_loads(model, tmp_path):
    onnx = pytest.importorskip("onnx")
    onnx_path, _, _ = model
    proto = onnx.load(str(onnx_path))
    keep = [p for p in proto.metadata_props if p.key != "graph_sha256"]
    del proto.metadata_props[:]
    proto.metadata_props.extend(keep)
    old = tmp_path / "old.onnx"
    old.write_bytes(proto.SerializeToString())
    res = _invoke(["info", old])
    assert res.exit_code == 0 and "no digest" in res.output
    from nehad.runtime.onnx_model import OnnxModel

    assert len(OnnxModel(old).gaussians(0.5)) == OnnxModel(onnx_path).num_gaussians


# ---------------------------------------------------------------------------------------------
# 7. the small ones


@pytest.mark.parametrize("suffix,needle", [(":-1", "frame index -1 out of range"),
                                           (":7", "frame index 7 out of range"),
                                           ("#x", "frame index 'x' is not a whole number")])
def test_view_index_out_of_range(model, tmp_path, suffix, needle):
    onnx_path, scene, _ = model
    view = f"{scene}/transforms_test.json{suffix}"
    _one_error(_invoke(["render", onnx_path, "--view", view, "--time", "0.5",
                        "-o", tmp_path / "x.png"]), needle)
    _one_error(_invoke(["video", onnx_path, "--path", view, "-o", tmp_path / "x.mp4",
                        "--frames", "2"]), needle)
    assert _listing(tmp_path) == []


def test_time_with_a_static_ply_is_noted(model, static_ply, tmp_path):
    _, scene, _ = model
    res = _invoke(["render", static_ply, "--view", f"{scene}/transforms_test.json:0",
                   "--time", "0.3", "-o", tmp_path / "x.png"])
    assert res.exit_code == 0, res.output
    assert "note: --time 0.3 is ignored" in res.stderr and "static 3DGS PLY" in res.stderr
    res = _invoke(["render", static_ply, "--view", f"{scene}/transforms_test.json:0",
                   "-o", tmp_path / "y.png"])
    assert res.exit_code == 0 and "note:" not in res.stderr
    res = _invoke(["ply", static_ply, "--time", "0.3", "-o", tmp_path / "z.ply"])
    assert res.exit_code == 0 and "static 3DGS PLY" in res.stderr


def test_append_metrics_drops_the_repeated_steps(tmp_path):
    from nehad import checkpoint

    for s in range(1, 11):
        checkpoint.append_metrics(tmp_path, {"step": s, "loss": s})
    with open(tmp_path / "metrics.jsonl", "a") as f:
        f.write('{"step": 11, "lo')  # torn by a kill
    checkpoint._LAST_LOGGED.clear()  # a new process resumes from the checkpoint at step 5
    for s in range(6, 13):
        checkpoint.append_metrics(tmp_path, {"step": s, "loss": -s})
    recs = [json.loads(ln) for ln in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in recs] == list(range(1, 13))
    assert [r["loss"] for r in recs[5:]] == [-s for s in range(6, 13)]
    # a second resume in the same process (steps go back again)
    checkpoint.append_metrics(tmp_path, {"step": 9, "loss": 0})
    recs = [json.loads(ln) for ln in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in recs] == list(range(1, 10))


def test_metrics_have_no_duplicates_after_resume(model, tmp_path):
    _, scene, _ = model
    run = tmp_path / "run"
    args = ["train", scene, "-o", run, "--preset", "test", "--quiet", "--set",
            "coarse.iterations=6", "--set", "fine.iterations=6", "--set", "train.log_interval=1",
            "--set", "train.checkpoint_interval=3", "--set", "train.keep_checkpoints=5"]
    assert _invoke(args).exit_code == 0
    first = [json.loads(ln)["step"] for ln in (run / "metrics.jsonl").read_text().splitlines()]
    assert first == list(range(1, 13))
    # as if killed at step 12 just before its checkpoint: resume from step 9
    for p in (run / "checkpoints").glob("step_*.pt"):
        if int(p.stem.split("_")[1]) > 9:
            p.unlink()
    res = _invoke([*args, "--resume"])
    assert res.exit_code == 0 and "resuming" in res.output, res.output
    steps = [json.loads(ln)["step"] for ln in (run / "metrics.jsonl").read_text().splitlines()]
    assert steps == list(range(1, 13))


def test_ctrl_c_on_train_says_how_to_continue(model, tmp_path):
    _, scene, _ = model
    run = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "nehad.cli.main", "train", str(scene), "-o",
                             str(run), "--preset", "test", "--quiet", "--set",
                             "fine.iterations=100000"], env=ENV, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.time() + 300
        while not list((run / "checkpoints").glob("step_*.pt")):
            assert proc.poll() is None, proc.stderr.read()
            assert time.time() < deadline
            time.sleep(0.2)
        time.sleep(0.5)
        proc.send_signal(signal.SIGINT)
        _, err = _communicate_or_dump(proc, 60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "Aborted!" not in err
    assert "keeps its checkpoint at step" in err and "--resume to continue" in err
    assert not (run / "model.pt").exists() and not _temps(run / "checkpoints")
    assert not (tmp_path / ".run.nehad-lock").exists()


def _communicate_or_dump(proc, timeout: float) -> tuple[str, str]:
    """proc.communicate(timeout); a process still running then is sent SIGUSR1 first (the CLI
    prints every thread's stack, cli/main.py) and killed, and the test fails showing where it
    hung."""
    try:
        return proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        stacks.kill_with_stacks(proc, f"still running {timeout:g} s after SIGINT")


# Runs the `nehad` executable (cli/main.py entry: its SIGINT handling) with one function
# replaced: from its `after`-th call on, it creates FLAG and never returns (a C call that hangs
# is what a Ctrl-C must still end; time.sleep keeps the main thread in C most of the time).
HANG_IN = """
import importlib, sys, time
target, after, flag = sys.argv[1], int(sys.argv[2]), sys.argv[3]
module, _, name = target.partition(":")
owner = importlib.import_module(module)
*path, attr = name.split(".")
for p in path:
    owner = getattr(owner, p)
real = getattr(owner, attr)
calls = [0]
def hang(*a, **k):
    calls[0] += 1
    if calls[0] <= after:
        return real(*a, **k)
    open(flag, "w").close()
    while True:
        time.sleep(0.05)
setattr(owner, attr, hang)
sys.argv = ["nehad", *sys.argv[4:]]
from nehad.cli.main import entry
entry(prog_name="nehad")
"""


def _start_hanging(tmp_path, target: str, after: int, args):
    flag = tmp_path / "hung.flag"
    proc = subprocess.Popen([sys.executable, "-c", HANG_IN, target, str(after), str(flag),
                             *map(str, args)], env=ENV, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    _wait_for_flag(proc, flag)
    flag.unlink()
    return proc


# command -> (function that hangs, calls before it hangs, args(model, out), exit status, message)
CTRL_C = {
    "train": ("nehad.trainer:Trainer.train_step", 25,
              lambda m, out: ["train", m[1], "-o", out / "run", "--preset", "test", "--quiet"],
              130, "keeps its checkpoint at step 20"),
    "render": ("nehad.runtime.render:write_all", 0,
               lambda m, out: ["render", m[0], "--view", f"{m[1]}/transforms_test.json:0",
                               "--time", "0.5", "-o", out / "x.png"],
               130, "interrupted: nehad render stopped"),
    "export": ("nehad.export.onnx_export:atomic_write_bytes", 0,
               lambda m, out: ["export", m[2], "-o", out / "m.onnx"],
               130, "interrupted: nehad export stopped"),
    "ply": ("nehad.runtime.ply:write_gaussian_ply", 1,
            lambda m, out: ["ply", m[0], "--frames", "3", "-o", out / "frames"],
            130, "interrupted: nehad ply stopped"),
    "video": ("nehad.runtime.distribute:render_frame_task", 1,
              lambda m, out: ["video", m[0], "-o", out / "v.mp4", "--frames", "4", "--workers",
                              "1", "--quiet"], 130, "1 of 4 frames are kept"),
    "batch": ("nehad.runtime.distribute:render_frame_task", 1,
              lambda m, out: ["batch", out.parent / "jobs.yaml", "--quiet", "--workers", "1"],
              130, "--resume to render only what is missing"),
}


@pytest.mark.parametrize("command", sorted(CTRL_C))
def test_ctrl_c_ends_every_command_with_its_message(model, tmp_path, command):
    target, after, args, status, message = CTRL_C[command]
    out = tmp_path / "out"
    out.mkdir()
    (tmp_path / "jobs.yaml").write_text(f"jobs:\n  - {{model: {model[0]}, output: out/b.mp4, "
                                        f"frames: 4}}\n")
    proc = _start_hanging(tmp_path, target, after, args(model, out))
    start = time.perf_counter()
    proc.send_signal(signal.SIGINT)
    _, err = _communicate_or_dump(proc, 30)
    seconds = time.perf_counter() - start
    assert proc.returncode == status, err
    assert message in err and "Traceback" not in err and "Aborted" not in err, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("interrupted"), err
    # train waits for the next step, then raises it anyway after DEFERRED_SECONDS (5 s)
    assert seconds < (12 if command == "train" else 6), seconds
    assert not [p for p in out.rglob("*") if ".tmp" in p.name or p.suffix in (".png", ".onnx")
                and p.parent == out]
    assert not list(tmp_path.rglob(".*.nehad-lock"))


def test_a_second_ctrl_c_ends_at_once(model, tmp_path):
    """The first Ctrl-C waits for the step (which here never returns); the second ends the
    process at once, by the kernel's default action."""
    _, scene, _ = model
    proc = _start_hanging(tmp_path, "nehad.trainer:Trainer.train_step", 25,
                          ["train", scene, "-o", tmp_path / "run", "--preset", "test",
                           "--quiet"])
    proc.send_signal(signal.SIGINT)
    time.sleep(0.5)
    assert proc.poll() is None  # still waiting for a safe point
    start = time.perf_counter()
    proc.send_signal(signal.SIGINT)
    _communicate_or_dump(proc, 10)
    assert proc.returncode == -signal.SIGINT
    assert time.perf_counter() - start < 2


def test_ctrl_c_stops_the_viewer(model):
    pytest.importorskip("viser")
    onnx_path, _, _ = model
    proc = subprocess.Popen([sys.executable, "-m", "nehad.cli.main", "view", str(onnx_path),
                             "--port", "0"], env=ENV, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.time() + 120
        for line in proc.stdout:  # the page's address is printed once the server is up
            if line.startswith("open http"):
                break
            assert time.time() < deadline
        assert proc.poll() is None, proc.stderr.read()
        start = time.perf_counter()
        proc.send_signal(signal.SIGINT)
        _, err = _communicate_or_dump(proc, 30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0 and "stopped" in err and "Traceback" not in err, err
    assert time.perf_counter() - start < 10


def test_interrupt_wrapped_by_a_library_is_still_ctrl_c():
    """numba returns a KeyboardInterrupt raised in its Python callback (_numba_unpickle) as a
    SystemError; the CLI still treats it as Ctrl-C."""
    from nehad.cli.errors import interrupted

    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as k:
            raise SystemError("returned a result with an exception set") from k
    except SystemError as e:
        assert interrupted(e)
    assert not interrupted(ValueError("x"))


def test_module_stays_torch_free():
    """The new runtime rooms (temp files, locks, memory) import nothing heavy."""
    code = ("import sys; import nehad.runtime.tempfiles, nehad.runtime.lock, "
            "nehad.runtime.memory; print('torch' in sys.modules)")
    proc = subprocess.run([sys.executable, "-c", code], env=ENV, capture_output=True, text=True)
    assert proc.stdout.strip() == "False", proc.stderr



def test_write_sequence_and_write_all_leave_nothing_on_a_failure(tmp_path):
    """runtime/render.py: a failure in the third file removes the two written before it (and
    the folder the call created); write_all removes its earlier outputs too."""
    from nehad.runtime.render import write_all, write_sequence

    def writer(k):
        def write(path):
            if k == 2:
                raise OSError(28, "No space left on device", str(path))
            path.write_text(str(k))
        return write

    folder = tmp_path / "frames"
    with pytest.raises(OSError):
        write_sequence(folder, ((f"f{k}.txt", writer(k)) for k in range(4)))
    assert not folder.exists()
    folder.mkdir()
    (folder / "keep.txt").write_text("mine")
    with pytest.raises(OSError):
        write_sequence(folder, ((f"f{k}.txt", writer(k)) for k in range(4)))
    assert sorted(p.name for p in folder.iterdir()) == ["keep.txt"]  # an existing folder stays
    assert write_sequence(folder, ((f"f{k}.txt", writer(k)) for k in range(2))) == 2
    with pytest.raises(OSError):
        write_all([(tmp_path / "a.png", np.zeros((4, 4, 3), np.float32)),
                   (tmp_path / "b.txt", writer(2))])
    assert not (tmp_path / "a.png").exists()


# ---------------------------------------------------------------------------------------------
# 8. issue 26: each class of bad input, across the commands that read it. Every case: a
# non-zero exit, exactly one `Error:` line holding the fragment, no traceback, nothing written.


def _clean_error(res, *needles) -> str:
    """Like _one_error, for click's own option errors too (exit 2; one `Error:` line as well,
    no `Usage:` lines: cli/main.py `_OneLineUsageError`)."""
    assert res.exit_code in (1, 2), (res.exit_code, res.output, res.exception)
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    errors = [ln for ln in lines if ln.startswith("Error")]
    assert len(errors) == 1 and len(lines) == 1, res.stderr
    for n in needles:
        assert n in errors[0], (n, errors[0])
    assert "Traceback" not in res.output
    return errors[0]


def _jobs(folder: Path, body: str) -> Path:
    path = folder / "jobs.yaml"
    path.write_text(textwrap.dedent(body))
    return path


# (case, args(model, out, inputs) -> argv, expected fragment); `out` must stay empty
NUMBERS = [
    ("synth --fixed-time nan", lambda m, out, inp: ["synth", out / "s", "--fixed-time", "nan"],
     "not a finite number"),
    ("synth --fixed-time inf", lambda m, out, inp: ["synth", out / "s", "--fixed-time", "inf"],
     "not a finite number"),
    ("train --set nan", lambda m, out, inp: ["train", m[1], "-o", out / "run", "--preset", "test",
                                              "--set", "optim.opacity_lr=nan"],
     "optim.opacity_lr: expected a finite number"),
    ("train --set .inf", lambda m, out, inp: ["train", m[1], "-o", out / "run", "--preset",
                                               "test", "--set", "fine.iterations=.inf"],
     "fine.iterations: expected an integer"),
    ("train --set negative lr", lambda m, out, inp: ["train", m[1], "-o", out / "run", "--preset",
                                                      "test", "--set", "optim.scaling_lr=-1"],
     "optim.scaling_lr: must be >= 0"),
    ("train --set ssim weight 2", lambda m, out, inp: ["train", m[1], "-o", out / "run",
                                                        "--preset", "test", "--set",
                                                        "loss.ssim_weight=2"],
     "loss.ssim_weight: must be in [0.0, 1.0]"),
    ("train --set checkpoint_interval 0", lambda m, out, inp: [
        "train", m[1], "-o", out / "run", "--preset", "test", "--set",
        "train.checkpoint_interval=0"], "train.checkpoint_interval: must be >= 1"),
    ("train --config .nan", lambda m, out, inp: ["train", m[1], "-o", out / "run", "--preset",
                                                  "test", "--config", inp["nan.yaml"]],
     "optim.rotation_lr: expected a finite number"),
    ("demo --set background nan", lambda m, out, inp: ["demo", "-o", out / "demo", "--set",
                                                        "data.background=[1,.nan,1]"],
     "data.background[1]: expected a finite number"),
    ("render --time nan", lambda m, out, inp: ["render", m[0], "--view",
                                               f"{m[1]}/transforms_test.json:0", "--time", "nan",
                                               "-o", out / "x.png"], "not a finite number"),
    ("ply --time inf", lambda m, out, inp: ["ply", m[0], "--time", "inf", "-o", out / "x.ply"],
     "not a finite number"),
    ("video --fps nan", lambda m, out, inp: ["video", m[0], "-o", out / "v.mp4", "--fps", "nan"],
     "not a finite number"),
    ("viz masks --threshold nan", lambda m, out, inp: ["viz", "masks", m[2], "--threshold",
                                                       "nan", "--plot", out / "p.png"],
     "not a finite number"),
    ("batch time .nan", lambda m, out, inp: ["batch", inp["time.yaml"]], "time: expected"),
    ("batch fps .inf", lambda m, out, inp: ["batch", inp["fps.yaml"]], "fps: expected a number"),
]


@pytest.fixture
def number_inputs(model, tmp_path):
    onnx_path, _, _ = model
    inp = tmp_path / "inputs"
    inp.mkdir()
    (inp / "nan.yaml").write_text("optim:\n  rotation_lr: .nan\n")
    (inp / "time.yaml").write_text(f"jobs:\n  - {{model: {onnx_path}, output: {tmp_path}/out/a.png,"
                                   f" time: .nan}}\n")
    (inp / "fps.yaml").write_text(f"jobs:\n  - {{model: {onnx_path}, output: {tmp_path}/out/a.mp4,"
                                  f" fps: .inf, frames: 2}}\n")
    return {p.name: p for p in inp.iterdir()}


@pytest.mark.parametrize("case,args,needle", NUMBERS, ids=[c[0] for c in NUMBERS])
def test_numbers_are_finite_and_in_range(model, tmp_path, number_inputs, case, args, needle):
    out = tmp_path / "out"
    out.mkdir()
    _clean_error(_invoke(args(model, out, number_inputs)), needle)
    assert _listing(out) == []


@pytest.mark.parametrize("args", [["synth", "{out}/s", "--resolution", "100000"],
                                  ["synth", "{out}/s", "--resolution", "100000", "--format",
                                   "hypernerf"],
                                  ["demo", "-o", "{out}/demo", "--resolution", "100000"]],
                         ids=["synth", "synth hypernerf", "demo"])
def test_synth_sizes_are_checked_against_memory(tmp_path, cap_16g, args):
    start = time.perf_counter()
    out = tmp_path / "out"
    out.mkdir()
    _one_error(_invoke([a.format(out=out) for a in args]), "--resolution 100000",
               "GB of memory", "NEHAD_MAX_FRAME_MEMORY=16G")
    assert time.perf_counter() - start < 20
    assert _listing(out) == []


SIZES = {
    "video --frames": ["video", "{model}", "-o", "{out}/v.mp4", "--frames", "30000000"],
    "video --frames spiral": ["video", "{model}", "--frames-dir", "{out}/f", "--frames",
                              "30000000", "--path", "spiral"],
    "video --workers": ["video", "{model}", "-o", "{out}/v.mp4", "--frames", "1000",
                        "--workers", "1000"],
    "viz trajectories --times": ["viz", "trajectories", "{model}", "--times", "100000000", "-o",
                                 "{out}/t.png"],
    "report --max-side": ["report", "{run}", "-o", "{out}/r.html", "--max-side", "100000000"],
}


@pytest.mark.parametrize("case", sorted(SIZES))
def test_frame_counts_are_checked_against_memory(model, tmp_path, cap_16g, case):
    start = time.perf_counter()
    out = tmp_path / "out"
    out.mkdir()
    args = SIZES[case]
    given = {"video --frames spiral": "30000000", "viz trajectories --times": "100000000"}.get(
        case, args[-1])
    _one_error(_invoke([a.format(out=out, model=model[0], run=model[2]) for a in args]),
               given, "GB of memory")
    assert time.perf_counter() - start < 20  # refused before planning them
    assert _listing(out) == []


# -- a full disk: a tmpfs filled to its last byte (as root); else a file size limit of 0 bytes
# (RLIMIT_FSIZE, writes fail with EFBIG), which is what a user without mount rights can test


@pytest.fixture(scope="module")
def full_disk(tmp_path_factory):
    """(folder, preexec_fn, reason): a folder on a file system that refuses every write."""
    folder = tmp_path_factory.mktemp("full")
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(folder)],
                             capture_output=True).returncode == 0
    if mounted:
        try:
            with open(folder / "filler", "wb", buffering=0) as f:
                for size in (4096, 1):  # to the last byte
                    with contextlib.suppress(OSError):
                        while f.write(b"\0" * size) == size:
                            pass
            yield folder, None, "No space left on device"
        finally:
            subprocess.run(["umount", "-l", str(folder)], capture_output=True)
        return

    def limit():
        import resource

        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (0, 0))

    (folder / "filler").write_bytes(b"")
    yield folder, limit, "File too large"


FULL_DISK = {
    "export": lambda m, out: ["export", m[2], "-o", out / "model.onnx"],
    "ply --frames": lambda m, out: ["ply", m[0], "--frames", "2", "-o", out / "frames"],
    "ply --time": lambda m, out: ["ply", m[0], "--time", "0.5", "-o", out / "x.ply"],
    "render": lambda m, out: ["render", m[0], "--view", f"{m[1]}/transforms_test.json:0",
                              "--time", "0.5", "-o", out / "x.png"],
    "render .exr": lambda m, out: ["render", m[0], "--view", f"{m[1]}/transforms_test.json:0",
                                   "--time", "0.5", "-o", out / "x.exr"],
    "video": lambda m, out: ["video", m[0], "-o", out / "v.mp4", "--frames", "2", "--workers",
                             "1", "--quiet"],
    "train": lambda m, out: ["train", m[1], "-o", out / "run", "--preset", "test", "--quiet"],
    "synth": lambda m, out: ["synth", out / "scene", "--resolution", "8", "--frames", "2"],
}


@pytest.mark.parametrize("command", sorted(FULL_DISK))
def test_a_full_disk_is_one_error_naming_the_file(model, full_disk, command):
    folder, preexec, reason = full_disk
    before = _listing(folder)
    proc = _run_cli(FULL_DISK[command](model, folder), preexec_fn=preexec)
    line = _proc_error(proc, str(folder), reason)
    assert ".tmp" not in line  # the file the user asked for, not the temporary one
    assert _listing(folder) == before  # temporary files removed, no folder left behind


BAD_UTF8 = os.fsdecode(b"bad-\xff\xfe")
NON_UTF8 = {
    "render -o": lambda m, d: ["render", m[0], "--view", f"{m[1]}/transforms_test.json:0",
                               "--time", "0.5", "-o", d / f"{BAD_UTF8}.png"],
    "ply -o": lambda m, d: ["ply", m[0], "--time", "0.5", "-o", d / f"{BAD_UTF8}.ply"],
    "video -o": lambda m, d: ["video", m[0], "-o", d / f"{BAD_UTF8}.mp4", "--frames", "2"],
    "export -o": lambda m, d: ["export", m[2], "-o", d / f"{BAD_UTF8}.onnx"],
    "synth OUT": lambda m, d: ["synth", d / BAD_UTF8],
    "train DATA": lambda m, d: ["train", d / BAD_UTF8, "-o", d / "run"],
    "batch JOBS": lambda m, d: ["batch", d / f"{BAD_UTF8}.yaml"],
    "render --view": lambda m, d: ["render", m[0], "--view", d / f"{BAD_UTF8}.json", "-o",
                                   d / "x.png"],
}


@pytest.mark.parametrize("case", sorted(NON_UTF8))
def test_paths_that_are_not_utf8_are_refused(model, tmp_path, case):
    _one_error(_invoke(NON_UTF8[case](model, tmp_path)), "b'", "not valid UTF-8")
    assert _listing(tmp_path) == []


NOT_REGULAR = {
    "train --config FIFO": lambda m, f, out: ["train", m[1], "-o", out / "run", "--preset",
                                              "test", "--config", f["fifo.yaml"]],
    "train --config /dev/zero": lambda m, f, out: ["train", m[1], "-o", out / "run", "--preset",
                                                   "test", "--config", "/dev/zero"],
    "render FIFO.ply": lambda m, f, out: ["render", f["fifo.ply"], "--view",
                                          f"{m[1]}/transforms_test.json:0", "-o", out / "x.png"],
    "ply FIFO.onnx": lambda m, f, out: ["ply", f["fifo.onnx"], "--time", "0.5", "-o",
                                        out / "x.ply"],
    "video FIFO.onnx": lambda m, f, out: ["video", f["fifo.onnx"], "-o", out / "v.mp4"],
    "info /dev/zero": lambda m, f, out: ["info", "/dev/zero"],
}


@pytest.mark.parametrize("case", sorted(NOT_REGULAR))
def test_devices_and_fifos_are_refused_not_read_forever(model, tmp_path, case):
    """A FIFO blocks its reader until someone writes; /dev/zero never ends."""
    fifos = {}
    for name in ("fifo.yaml", "fifo.ply", "fifo.onnx"):
        os.mkfifo(tmp_path / name)
        fifos[name] = tmp_path / name
    out = tmp_path / "out"
    out.mkdir()
    proc = _run_cli(NOT_REGULAR[case](model, fifos, out), timeout=60)
    _proc_error(proc, "not a regular file")
    assert _listing(out) == []


def _output_is_input_cases(model, d: Path) -> dict:
    onnx_path, scene, _ = model
    ply = d / "g.ply"
    shutil.copy(onnx_path.parent / "run" / "config.yaml", d / "config.yaml")
    view = d / "cam.json"
    shutil.copy(scene / "transforms_test.json", view)
    frames = d / "frames"
    frames.mkdir()
    from nehad.data.synth_gaussians import scene_gaussians
    from nehad.runtime.ply import write_gaussian_ply

    write_gaussian_ply(ply, scene_gaussians("spheres", 0.5, 50))
    shutil.copy(ply, frames / "frame_0000.ply")
    (d / "link.png").symlink_to(ply)
    (d / "cam.png").symlink_to(view)
    jobs_png = _jobs(d, f"""\
        jobs:
          - {{model: {onnx_path}, output: j.png, time: 0.5}}
        """).rename(d / "j.png")
    view_job = d / "view_job.yaml"
    view_job.write_text(f"jobs:\n  - {{model: {onnx_path}, output: cam.png, view: 'cam.json:0', "
                        f"time: 0.5}}\n")
    model_job = d / "model_job.yaml"
    model_job.write_text(f"jobs:\n  - {{model: {onnx_path}, output: x.png, time: 0.5}}\n"
                         f"  - {{model: g.ply, output: link.png, view: 'cam.json:0'}}\n")
    return {
        "ply -o SCENE": (["ply", ply, "--time", "0", "-o", ply], ply),
        "ply --frames into SCENE's folder": (["ply", frames / "frame_0000.ply", "--frames", "2",
                                              "-o", frames], frames / "frame_0000.ply"),
        "render -o (a link to) SCENE": (["render", ply, "--view", f"{view}:0", "-o",
                                         d / "link.png"], ply),
        "render -o (a link to) --view": (["render", ply, "--view", f"{view}:0", "-o",
                                          d / "cam.png"], view),
        "batch: the jobs file is an output": (["batch", jobs_png, "--quiet"], jobs_png),
        "batch: a job's view is an output": (["batch", view_job, "--quiet"], view),
        "batch: a job's model is an output": (["batch", model_job, "--quiet"], ply),
        "batch --check": (["batch", jobs_png, "--check"], jobs_png),
    }


OUTPUT_IS_INPUT = ["ply -o SCENE", "ply --frames into SCENE's folder",
                   "render -o (a link to) SCENE", "render -o (a link to) --view",
                   "batch: the jobs file is an output", "batch: a job's view is an output",
                   "batch: a job's model is an output", "batch --check"]


@pytest.mark.parametrize("case", OUTPUT_IS_INPUT)
def test_an_output_that_is_an_input_is_refused(model, tmp_path, case):
    args, victim = _output_is_input_cases(model, tmp_path)[case]
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    _one_error(_invoke(args), "is also an input")
    after = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    assert after == before and victim in after


# -- files a command reads from a run folder


def _damage(run: Path, what: str) -> None:
    if what == "config.yaml":
        (run / "config.yaml").write_bytes(b"preset: test\n\xff\xfe\x00binary")
    elif what == "metrics.jsonl":
        (run / "metrics.jsonl").write_bytes(b'{"step": 1}\n\x89PNG\r\n\x1a\n\xff\x00')
    elif what == "eval metrics.json":
        (run / "eval_test").mkdir(exist_ok=True)
        (run / "eval_test" / "metrics.json").write_bytes(b"\xff\xd8\xff\xe0 jpeg")
    elif what == "last checkpoint":
        last = sorted((run / "checkpoints").glob("step_*.pt"))[-1]
        last.write_bytes(last.read_bytes()[:100])
    elif what == "model.pt as the last checkpoint":
        last = sorted((run / "checkpoints").glob("step_*.pt"))[-1]
        shutil.copy(run / "model.pt", last.with_name("step_9999999.pt"))
    elif what == "eval metrics.json of other types":
        (run / "eval_test").mkdir(exist_ok=True)
        (run / "eval_test" / "metrics.json").write_text('{"mean": "high", "objects": 3}')


RUN_FILES = [
    ("train --resume", "config.yaml", "config.yaml: not a UTF-8 text file"),
    ("train --resume", "last checkpoint", "truncated or corrupt"),
    ("report", "config.yaml", "config.yaml: not a UTF-8 text file"),
    ("report", "metrics.jsonl", "metrics.jsonl: not a UTF-8 text file"),
    ("report", "eval metrics.json", "metrics.json: not a UTF-8 text file"),
    ("train --resume", "model.pt as the last checkpoint", "not a training checkpoint"),
    ("report", "eval metrics.json of other types", "not the JSON object nehad eval writes"),
]


@pytest.mark.parametrize("command,what,needle", RUN_FILES,
                         ids=[f"{c} {w}" for c, w, _ in RUN_FILES])
def test_run_folder_files_are_read_with_clean_errors(model, tmp_path, command, what, needle):
    _, scene, run = model
    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    _damage(copy, what)
    before = {p: p.read_bytes() for p in copy.rglob("*") if p.is_file()}
    out = tmp_path / "out"
    out.mkdir()
    args = {"train --resume": ["train", scene, "-o", copy, "--preset", "test", "--resume",
                               "--quiet"],
            "report": ["report", copy, "-o", out / "r.html", "--frames", "1", "--no-score",
                       "--max-side", "32"]}[command]
    _one_error(_invoke(args), str(copy), needle)
    assert {p: p.read_bytes() for p in copy.rglob("*") if p.is_file()} == before
    assert _listing(out) == []


@pytest.mark.parametrize("host,needle", [("999.999.999.999", "not a valid IP address"),
                                         ("1.2.3", "not a valid IP address"),
                                         ("no-such-host.invalid", "unknown host")])
def test_view_refuses_a_bad_host_promptly(model, host, needle):
    pytest.importorskip("viser")
    onnx_path, _, _ = model
    start = time.perf_counter()
    proc = _run_cli(["view", onnx_path, "--host", host, "--port", "0"], timeout=60)
    _proc_error(proc, f"--host {host!r}" if needle.startswith("not") else f"--host {host}",
                needle)
    assert time.perf_counter() - start < 30


# ---------------------------------------------------------------------------------------------
# inputs a fuzzing pass found (2026-11-26): each ends in one error line naming the input


def _deep_json(path: Path) -> Path:
    path.write_text("[" * 100000 + "]" * 100000)
    return path


def test_parsers_refuse_deep_nesting_and_huge_numbers(model, tmp_path):
    onnx_path, _, _ = model
    out = tmp_path / "out"
    out.mkdir()
    render = ["render", onnx_path, "--time", "0.5", "-o", out / "x.png", "--view"]
    _one_error(_invoke(render + [_deep_json(tmp_path / "deep.json")]), "deep.json",
               "nested too deeply")
    huge = tmp_path / "huge.json"
    huge.write_text('{"width": ' + "7" * 5000 + ', "height": 10}')
    _one_error(_invoke(render + [huge]), "huge.json", "malformed JSON")
    cfg = tmp_path / "deep.yaml"
    cfg.write_text("a: " + "[" * 5000 + "]" * 5000 + "\n")
    _one_error(_invoke(["train", tmp_path, "-o", out / "r", "--config", cfg]), "deep.yaml")
    big = tmp_path / "big.yaml"
    big.write_text("fine:\n  iterations: " + "7" * 5000 + "\n")
    _one_error(_invoke(["train", tmp_path, "-o", out / "r", "--config", big]), "big.yaml")
    jobs = tmp_path / "jobs.yaml"
    jobs.write_text("jobs:\n  - {type: video, model: m.onnx, frames: " + "7" * 5000 + "}\n")
    _one_error(_invoke(["batch", jobs, "--check"]), "jobs.yaml")
    _one_error(_invoke(["train", tmp_path, "-o", out / "r", "--set",
                        "fine.iterations=" + "7" * 5000]), "fine.iterations")
    _one_error(_invoke(["train", tmp_path, "-o", out / "r", "--set",
                        "field.resolution=[100000,100000,8,4]"]), "resolution", "GiB")
    _one_error(_invoke(["train", tmp_path, "-o", out / "r", "--set", "preset=paper"]),
               "preset=paper", "--preset")
    assert _listing(out) == []


def test_a_dataset_with_frames_of_two_sizes_is_refused_naming_the_image(model, tmp_path):
    from PIL import Image

    _, scene, _ = model
    data = tmp_path / "data"
    shutil.copytree(scene, data)
    Image.new("RGBA", (16, 16)).save(data / "train" / "r_001.png")
    _one_error(_invoke(["train", data, "-o", tmp_path / "run", "--preset", "test", "--quiet"]),
               "r_001.png", "16x16")
    assert not (tmp_path / "run").exists()


def test_frame_rates_and_frame_counts_are_refused_before_any_work(model, tmp_path):
    onnx_path, _, _ = model
    out = tmp_path / "out"
    out.mkdir()
    _one_error(_invoke(["video", onnx_path, "--frames", "2", "--fps", "0.0005",
                        "-o", out / "v.mp4"]), "--fps")
    _one_error(_invoke(["prepare", tmp_path, "-o", out / "p", "--fps", "nan"]), "--fps")
    _one_error(_invoke(["ply", onnx_path, "--frames", str(10**12), "-o", out / "plys"]),
               "plys", "--frames", "No space left on device")
    assert _listing(out) == []


def test_a_failed_sequence_keeps_the_files_it_did_not_create(tmp_path):
    from nehad.runtime.render import write_sequence

    (tmp_path / "frame_0000.ply").write_text("the user's")

    def items():
        yield "frame_0000.ply", lambda p: Path(p).write_text("new")
        yield "frame_0001.ply", lambda p: Path(p).write_text("new")
        raise OSError("the model failed at the third time")

    with pytest.raises(OSError):
        write_sequence(tmp_path, items())
    assert _listing(tmp_path) == ["frame_0000.ply"]


def test_report_reads_a_log_with_values_of_other_types(model, tmp_path):
    """Values of other types are shown as n/a; a torn last line (a kill during the append) is
    skipped, as --resume drops it."""
    _, _, run = model
    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    with open(copy / "metrics.jsonl", "a") as f:
        f.write('{"step": 2, "psnr": [1], "loss": "x"}\n{"step": 3, "lo')
    res = _invoke(["report", copy, "-o", tmp_path / "r.html", "--frames", "0", "--no-score",
                   "--max-side", "32"])
    assert res.exit_code == 0, res.output
    assert "No test renders: --frames 0" in (tmp_path / "r.html").read_text()


@pytest.mark.parametrize("line, needle", [
    ("{not json", "not valid JSON"), ('{"step": NaN}', "its step is not a whole number"),
    ('{"step": "three"}', "its step is not a whole number"), ("[1, 2]", "not a JSON object")])
def test_report_names_a_damaged_log_line(model, tmp_path, line, needle):
    """A line of metrics.jsonl that is not a record nehad train writes, followed by another
    line (so not a torn last one), is one error naming the file and the line."""
    _, _, run = model
    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    lines = (copy / "metrics.jsonl").read_text().splitlines()
    lines.insert(1, line)
    (copy / "metrics.jsonl").write_text("\n".join(lines) + "\n")
    _one_error(_invoke(["report", copy, "-o", tmp_path / "r.html", "--frames", "0",
                        "--no-score"]), f"{copy / 'metrics.jsonl'}: line 2: {needle}")
    assert not (tmp_path / "r.html").exists()


def test_a_dataset_image_with_nan_pixels_is_refused_naming_it(model, tmp_path):
    from nehad.runtime.images import write_image

    _, scene, _ = model
    data = tmp_path / "data"
    shutil.copytree(scene, data)
    doc = json.loads((data / "transforms_train.json").read_text())
    doc["frames"][1]["file_path"] = "./train/nan.exr"
    (data / "transforms_train.json").write_text(json.dumps(doc))
    write_image(data / "train" / "nan.exr", np.full((32, 32, 4), np.nan, np.float32))
    _one_error(_invoke(["train", data, "-o", tmp_path / "run", "--preset", "test", "--quiet"]),
               "nan.exr", "NaN")
    assert not (tmp_path / "run").exists()


def test_a_png_cut_short_is_one_error_and_no_libpng_line(model, tmp_path, capfd):
    """libpng prints its own line on a truncated PNG; the file is refused before it decodes.
    A PNG with bytes after its IEND chunk still reads."""
    from nehad.runtime.images import png_cut_short, read_image

    _, scene, _ = model
    data = tmp_path / "data"
    shutil.copytree(scene, data)
    png = data / "train" / "r_001.png"
    whole = png.read_bytes()
    png.write_bytes(whole[: len(whole) * 2 // 3])
    capfd.readouterr()
    _one_error(_invoke(["train", data, "-o", tmp_path / "run", "--preset", "test", "--quiet"]),
               "r_001.png", "cut short")
    assert "libpng" not in capfd.readouterr().err
    tail = tmp_path / "tail.png"
    tail.write_bytes(whole + b"trailing bytes")
    assert png_cut_short(tail) is None and read_image(tail).shape == read_image(
        scene / "train" / "r_001.png").shape


def test_training_refuses_the_scaled_camera_that_render_refuses(model, tmp_path):
    _, scene, _ = model
    data = tmp_path / "data"
    shutil.copytree(scene, data)
    doc = json.loads((data / "transforms_train.json").read_text())
    m = np.asarray(doc["frames"][2]["transform_matrix"])
    m[:3, :3] *= 2.0
    doc["frames"][2]["transform_matrix"] = m.tolist()
    (data / "transforms_train.json").write_text(json.dumps(doc))
    _one_error(_invoke(["train", data, "-o", tmp_path / "run", "--preset", "test", "--quiet"]),
               "frames[2].transform_matrix", "not orthonormal")
    cam = tmp_path / "cam.json"
    cam.write_text(json.dumps({"width": 32, "height": 32, "fov_x": 0.7,
                               "camera_to_world": m.tolist(), "convention": "opengl"}))
    _one_error(_invoke(["render", model[0], "--view", cam, "--time", "0.5",
                        "-o", tmp_path / "x.png"]), "not orthonormal")


def test_a_time_beyond_float32_is_refused_even_when_extrapolating(model, tmp_path):
    _one_error(_invoke(["render", model[0], "--view", "default", "--time", "1e308",
                        "--extrapolate", "-o", tmp_path / "x.png"]), "--time", "float32")
    assert not (tmp_path / "x.png").exists()


def test_info_refuses_a_model_that_render_refuses(model, tmp_path):
    """A file whose metadata says 7 Gaussians where its outputs hold 2000: `render` refused
    it and `info` described it. (Its static_gaussians, above 7, is taken out: it would be
    refused first, when the file is read.)"""
    import onnx

    proto = onnx.load(str(model[0]))
    for prop in proto.metadata_props:
        if prop.key == "num_gaussians":
            prop.value = "7"
    props = [(p.key, p.value) for p in proto.metadata_props if p.key != "static_gaussians"]
    del proto.metadata_props[:]
    for key, value in props:
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
    bad = tmp_path / "bad.onnx"
    onnx.save(proto, str(bad))
    for command in (["info", bad], ["render", bad, "--view", "default", "--time", "0.5",
                                    "-o", tmp_path / "x.png"]):
        _one_error(_invoke(command), "bad.onnx", "num_gaussians 7")


# ---------------------------------------------------------------------------------------------
# the fuzzing pass of 2026-11-27: each input below ended in a traceback, a library's warning
# line, an exit status 0 or a file left behind


def test_a_downscale_larger_than_the_images_is_one_error(model, tmp_path):
    _, scene, _ = model
    _one_error(_invoke(["train", scene, "-o", tmp_path / "run", "--preset", "test", "--quiet",
                        "--set", "data.downscale=1000"]), "data.downscale 1000", "no pixel left")


@pytest.mark.parametrize("points", [1, 2])
def test_training_starts_from_one_or_two_points(model, tmp_path, points):
    """3DGS sizes each starting Gaussian by its 3 nearest neighbours: with fewer points, by
    those there are (a lone point: 0.01)."""
    from nehad.gaussians import _nearest_neighbour_distance

    assert _nearest_neighbour_distance(np.zeros((1, 3)))[0] == pytest.approx(0.01)
    assert _nearest_neighbour_distance(np.array([[0, 0, 0], [3, 4, 0]], float)) == \
        pytest.approx([5.0, 5.0])
    _, scene, _ = model
    res = _invoke(["train", scene, "-o", tmp_path / "run", "--preset", "test", "--quiet",
                   "--set", f"train.init_max_points={points}", "--set", "coarse.iterations=3",
                   "--set", "fine.iterations=3"])
    assert res.exit_code == 0 and not res.stderr.strip(), res.output


@pytest.mark.filterwarnings("error::RuntimeWarning")  # numpy's cast warning fails the command
def test_a_diverged_training_is_one_error_without_numpy_lines(model, tmp_path, capfd):
    _, scene, _ = model
    capfd.readouterr()
    _one_error(_invoke(["train", scene, "-o", tmp_path / "run", "--preset", "test", "--quiet",
                        "--set", "field.dt=1e30", "--set", "coarse.iterations=3",
                        "--set", "fine.iterations=3"]), "the loss became nan")
    assert "RuntimeWarning" not in capfd.readouterr().err


@pytest.mark.parametrize("option,needle", [
    ("train.revive_opacity=2", "train.revive_opacity: must be in [0.0, 0.99]"),
    ("train.drift_window=-1", "train.drift_window: must be >= 0.0"),
])
def test_config_values_out_of_their_range_or_choices(model, tmp_path, option, needle):
    _, scene, _ = model
    _one_error(_invoke(["train", scene, "-o", tmp_path / "run", "--preset", "test", "--quiet",
                        "--set", option]), needle)
    assert not (tmp_path / "run").exists()


def test_a_config_file_names_its_preset(model, tmp_path):
    """A run's config.yaml records its preset: reused with --config it is built on that preset
    (it was ignored, the settings merged onto cpu's); a different --preset beside it is
    refused."""
    _, scene, _ = model
    first = tmp_path / "first"
    res = _invoke(["train", scene, "-o", first, "--preset", "test", "--quiet",
                   "--set", "coarse.iterations=3", "--set", "fine.iterations=3"])
    assert res.exit_code == 0, res.output
    res = _invoke(["train", scene, "-o", tmp_path / "again", "--quiet",
                   "--config", first / "config.yaml"])
    assert res.exit_code == 0, res.output
    assert (first / "config.yaml").read_text() == (tmp_path / "again" / "config.yaml").read_text()
    _one_error(_invoke(["train", scene, "-o", tmp_path / "run", "--preset", "paper", "--quiet",
                        "--config", first / "config.yaml"]),
               "config.yaml", "preset 'test', but --preset paper")
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("path,needle", [
    ("orbit:turns=1e308", "turns=1e308: must be within +-1e6"),
    ("orbit:radius=1e300", "radius=1e300: must be positive, at most 1e9"),
    ("orbit:centre=[1e300,0,0]", "each number must be within +-1e9"),
])
def test_orbit_numbers_too_large_for_the_geometry(model, tmp_path, path, needle):
    _one_error(_invoke(["video", model[0], "--frames", "2", "--size", "16x16", "--workers", "1",
                        "-o", tmp_path / "v.mp4", "--path", path]), needle)
    assert not list(tmp_path.iterdir())


def test_a_slow_frame_rate_in_range_is_encoded():
    """0.0013 fps was read as the NTSC rate 0/1001 and refused after every frame was drawn."""
    from fractions import Fraction

    from nehad.runtime.mp4 import video_rate

    assert video_rate(0.0013) == Fraction(1, 769) and video_rate(0.001) == Fraction(1, 1000)
    assert video_rate(29.97) == Fraction(30000, 1001) and video_rate(0.5) == Fraction(1, 2)


@pytest.mark.parametrize("args,needle", [
    (["render", "{m}", "--size", "0x0", "-o", "{o}/a.png"], "Invalid value for '--size'"),
    (["render", "{m}", "--background", "2,0,0", "-o", "{o}/a.png"], "'--background'"),
    (["export", "{o}"], "give -o MODEL.onnx"),
    (["info", "{o}"], "is a directory"),
    (["no-such-command"], "No such command"),
])
def test_usage_errors_are_one_line(model, tmp_path, args, needle):
    res = _invoke([a.format(m=model[0], o=tmp_path) for a in args])
    assert res.exit_code == 2, res.output
    line = _clean_error(res, needle)
    assert "--help" in line and "Usage:" not in res.output


@pytest.mark.parametrize("args", [[], ["viz"]])
def test_a_group_without_a_command_still_shows_its_help(args):
    res = _invoke(args)
    assert res.output.startswith("Usage: ") and "Error" not in res.output, res.output
    assert "Commands:" in res.output


def test_eval_with_an_unreadable_mask_leaves_no_empty_folder(model, tmp_path):
    _, scene, run = model
    data, copy = tmp_path / "data", tmp_path / "run"
    shutil.copytree(scene, data)
    shutil.copytree(run, copy, ignore=shutil.ignore_patterns("eval_*"))
    masks = sorted((data / "test" / "masks").glob("*.png"))
    assert masks
    masks[0].write_bytes(b"not a png")
    line = _one_error(_invoke(["eval", copy, "--data", data, "--no-lpips", "--quiet"]),
                      "cannot read the label mask")
    assert line.count(str(masks[0])) == 1, line
    assert not (copy / "eval_test").exists()


def test_batch_check_finds_what_the_jobs_would_fail_on(model, tmp_path):
    m = model[0]
    for body, needle in [
        (f"jobs: [{{model: {tmp_path}/nowhere.onnx, output: a.png, time: 0.5}}]",
         "nowhere.onnx: no such file or folder"),
        (f"jobs: [{{model: {m}, output: no/a.png, time: 0.5}}]", "folder"),
        (f"jobs: [{{model: {m}, output: a.png, time: '0:1'}}]", "an image job renders one time"),
        (f"jobs: [{{model: {m}, output: a.png, lod: 3}}]", "has 1 layer(s)"),
    ]:
        jobs = _jobs(tmp_path, body)
        _one_error(_invoke(["batch", jobs, "--check"]), needle)



# ---------------------------------------------------------------------------------------------
# inputs a fuzzing pass found (2026-11-27): each ended in a traceback (or a hang)


@pytest.mark.parametrize("args,needle", [
    (["video", "{m}", "--workers", str(10**20)], f"--workers {10**20}: must be a whole number"),
    (["video", "{m}", "--threads", str(10**20)], f"--threads {10**20}: must be a whole number"),
    (["video", "{m}", "--threads", "5000"], "--threads 5000: must be a whole number in 1..1024"),
])
def test_worker_and_thread_counts_too_large_for_the_os(model, tmp_path, args, needle):
    """--workers 10**20 was an OverflowError of multiprocessing, --threads 10**20 a TypeError of
    onnxruntime, --threads 100000 started that many onnxruntime threads (no end in sight)."""
    argv = [a.format(m=model[0]) for a in args]
    _one_error(_invoke(argv + ["--frames", "2", "--size", "16x16", "-o", tmp_path / "v.mp4"]),
               needle)
    jobs = _jobs(tmp_path, f"workers: {10**20}\njobs: [{{model: {model[0]}, output: a.png}}]\n")
    _one_error(_invoke(["batch", jobs, "--check"]), "jobs.yaml", "workers", "1..1024")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["jobs.yaml"]


def test_view_refuses_a_thread_count_before_serving(model):
    pytest.importorskip("viser")
    proc = _run_cli(["view", model[0], "--threads", "5000", "--port", "0"], timeout=60)
    _proc_error(proc, "--threads 5000: must be a whole number in")


@pytest.mark.parametrize("option,needle", [
    ("field.width=1e9", "the deformation network would hold about 5e+18 weights"),
    ("field.hnn_hidden=1000000000", "field.hnn_hidden (1000000000)"),
    ("field.depth=1000000", "field.depth: 1000000 layers; at most 64"),
    ("field.hnn_depth=1000000", "field.hnn_depth: 1000000 layers; at most 64"),
    ("coarse.batch_size=1000000000", "coarse.batch_size: must be in 1..1024"),
])
def test_a_network_too_large_to_build_is_refused_before_it_is(model, tmp_path, option, needle):
    """width 1e9 was a traceback of torch's allocator; depth 1000000 built layers for minutes;
    a batch of 10**9 views asked numpy for 8 GB of indices, then drew for ever."""
    _, scene, _ = model
    start = time.perf_counter()
    _one_error(_invoke(["train", scene, "-o", tmp_path / "run", "--preset", "test", "--quiet",
                        "--set", option]), needle)
    assert time.perf_counter() - start < 30 and not (tmp_path / "run").exists()


def test_a_rig_capture_counts_its_cameras_against_memory(tmp_path, cap_16g):
    """--capture rig --cameras 10**20 passed the memory check (frames only) and drew forever."""
    start = time.perf_counter()
    _one_error(_invoke(["synth", tmp_path / "s", "--capture", "rig", "--cameras", str(10**20),
                        "--resolution", "16", "--frames", "2"]),
               f"--frames 2 with --cameras {10**20}", "GB of memory")
    assert time.perf_counter() - start < 20 and not (tmp_path / "s").exists()


def test_nehad_threads_beyond_the_bound_is_one_error(model, tmp_path, monkeypatch):
    monkeypatch.setenv("NEHAD_THREADS", str(10**20))
    _one_error(_invoke(["video", model[0], "--frames", "2", "--size", "16x16", "--workers", "1",
                        "-o", tmp_path / "v.mp4"]), "NEHAD_THREADS=", "at most 1024")


@pytest.mark.parametrize("args,needle", [
    (["viz", "trajectories", "{m}", "-o", "{o}/t.png", "--size", "32768x32768"],
     "--size 32768x32768: a 32768x32768 frame"),
    (["viz", "masks", "{r}", "-o", "{o}/m.png", "--size", "32768x32768"],
     "--size 32768x32768: a 32768x32768 frame"),
    (["viz", "masks", "{r}", "--plot", "{o}/p.png", "--times", str(10**20)],
     f"--times {10**20}: the BED weights"),
])
def test_viz_pictures_and_times_are_checked_against_memory(model, tiny_run, tmp_path, cap_16g,
                                                           args, needle):
    """viz drew these without the memory bound: --size 32768x32768 was killed by the OOM
    killer, viz masks --times 10**20 a traceback of numpy's linspace. (`viz masks` reads a run
    trained with the BED masks: tests/conftest.py's tiny_run.)"""
    out = tmp_path / "out"
    out.mkdir()
    argv = [a.format(m=model[0], r=tiny_run[1], o=out) for a in args]
    _one_error(_invoke(argv), needle, "GB of memory")
    assert _listing(out) == []


@pytest.mark.parametrize("body", ["[]", "[" * 100000 + "]" * 100000])
def test_video_resume_with_a_frame_manifest_that_is_not_an_object(model, tmp_path, body):
    """A nehad-frames.json holding a list was an AttributeError ('list' has no 'get'), one
    nested too deeply a RecursionError."""
    frames = tmp_path / "frames"
    argv = ["video", model[0], "--frames", "3", "--size", "16x16", "--workers", "1",
            "--frames-dir", frames]
    assert _invoke(argv).exit_code == 0
    (frames / "nehad-frames.json").write_text(body)
    _one_error(_invoke(argv + ["--resume"]), str(frames), "no readable nehad-frames.json")


def _layer_entry(k, **kw):
    return {"layer": k, "file": "base.onnx" if k == 0 else f"layer_{k}.bin", "bytes": 10,
            "sha256": "0" * 64, "gaussians": 5, **kw}


@pytest.mark.parametrize("entry,needle", [
    (_layer_entry(1, layer="abc"), "layers[1].layer is 'abc'"),
    (_layer_entry(1, layer=None), "layers[1].layer is None"),
    (_layer_entry(1, file=3), "layers[1].file 3 must be a plain file name"),
    (_layer_entry(1, file=".."), "layers[1].file '..' must be a plain file name"),
    (_layer_entry(1, bytes="x"), "layers[1].bytes: expected a whole number >= 0, got 'x'"),
    (_layer_entry(1, gaussians="x"), "layers[1].gaussians: expected a whole number"),
    (_layer_entry(1, sha256=3), "layers[1].sha256: expected a hex digest"),
    ("deep", "nested too deeply"),
])
def test_a_layer_manifest_with_fields_of_other_types(tmp_path, entry, needle):
    """A split-layer folder's manifest.json with a layer number 'abc', a file name 3 or '..'
    (web: shutil.SameFileError), ... were tracebacks of int() and Path()."""
    folder = tmp_path / "layers"
    folder.mkdir()
    man = folder / "manifest.json"
    if entry == "deep":
        man.write_text("[" * 100000 + "]" * 100000)
    else:
        man.write_text(json.dumps({"format": "nehad-layers/1", "base": "base.onnx",
                                   "layers": [_layer_entry(0), entry]}))
    _one_error(_invoke(["render", folder, "--view", "default", "-o", tmp_path / "x.png"]),
               str(man), needle)
    _one_error(_invoke(["web", folder, "-o", tmp_path / "web"]), str(man), needle)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["layers"]


def test_run_and_dataset_json_nested_too_deeply(model, tmp_path):
    """A line of metrics.jsonl, an eval_*/metrics.json or a class_mapping.json nested thousands
    deep was a RecursionError of json in `nehad report` and `nehad eval`."""
    _, scene, run = model
    data, copy = tmp_path / "data", tmp_path / "run"
    shutil.copytree(scene, data)
    shutil.copytree(run, copy, ignore=shutil.ignore_patterns("eval_*"))
    deep = "[" * 100000 + "]" * 100000
    log = (copy / "metrics.jsonl").read_text()
    with open(copy / "metrics.jsonl", "a") as f:
        f.write(deep + "\n")
    _one_error(_invoke(["report", copy, "-o", tmp_path / "r.html", "--frames", "0",
                        "--no-score"]), "metrics.jsonl: line", "nested too deeply")
    (copy / "metrics.jsonl").write_text(log)
    (copy / "eval_test").mkdir()
    (copy / "eval_test" / "metrics.json").write_text(deep)
    _one_error(_invoke(["report", copy, "-o", tmp_path / "r.html", "--frames", "0",
                        "--no-score"]), "eval_test/metrics.json", "nested too deeply")
    shutil.rmtree(copy / "eval_test")
    (data / "class_mapping.json").write_text(deep)
    _one_error(_invoke(["eval", copy, "--data", data, "--no-lpips", "--quiet"]),
               "class_mapping.json", "expected a JSON object of id -> name")
    assert not (tmp_path / "r.html").exists() and not (copy / "eval_test").exists()


@pytest.mark.parametrize("key,value,commands", [
    ("lod_layers", "abc", ["render", "info"]),
    ("lod_layers", '["a"]', ["render", "info"]),
    ("static_gaussians", "x", ["web", "info"]),
])
def test_model_metadata_of_other_types(model, tmp_path, key, value, commands):
    """An .onnx whose metadata lod_layers is not a list of counts was a JSONDecodeError of
    `nehad render`; static_gaussians 'x' a ValueError of `nehad web` (the metadata is outside
    the digest)."""
    onnx = pytest.importorskip("onnx")
    m = onnx.load(str(model[0]))
    props = {p.key: p.value for p in m.metadata_props}
    props[key] = value
    del m.metadata_props[:]
    for k, v in props.items():
        entry = m.metadata_props.add()
        entry.key, entry.value = k, v
    path = tmp_path / "m.onnx"
    onnx.save(m, str(path))
    argv = {"render": ["render", path, "--view", "default", "-o", tmp_path / "x.png"],
            "info": ["info", path], "web": ["web", path, "-o", tmp_path / "web"]}
    for c in commands:
        res = _invoke(argv[c])
        _one_error(res, "m.onnx: metadata", key)
        assert "Gaussians:" not in res.output  # info prints nothing before the error
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.onnx"]


def test_a_key_written_twice_is_refused(tmp_path, model):
    """A config or jobs file with one key twice in a mapping (PyYAML keeps the last and ran
    with the first unseen) is one error naming the key and its line; merge keys may still be
    overridden, as YAML means them (nehad.runtime.yamlfile)."""
    from nehad.runtime.yamlfile import load_yaml_text

    _, scene, _ = model
    cfg = tmp_path / "c.yaml"
    cfg.write_text("fine:\n  iterations: 5\n  densify_until: 3\n  iterations: 6\n")
    res = _invoke(["train", scene, "-o", tmp_path / "run", "--config", cfg, "--preset", "test"])
    _one_error(res, "c.yaml", "line 4", "'iterations' is written twice")
    assert not (tmp_path / "run").exists()
    jobs = tmp_path / "jobs.yaml"
    jobs.write_text("jobs:\n  - model: m.onnx\n    output: a.mp4\n    output: b.mp4\n")
    _one_error(_invoke(["batch", jobs]), "jobs.yaml", "line 4", "'output' is written twice")
    doc = load_yaml_text("base: &b {x: 1, y: 2}\nuse:\n  <<: *b\n  x: 3\n")
    assert doc["use"] == {"x": 3, "y": 2}
    assert load_yaml_text("a: {b: 1}\nc: {b: 2}\n") == {"a": {"b": 1}, "c": {"b": 2}}
