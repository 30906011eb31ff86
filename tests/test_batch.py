"""`nehad batch jobs.yaml` (nehad.runtime.batch, issue 5): the schema check names the job and
the key, a failing job does not stop the others, the summary and the exit status."""

from __future__ import annotations

import textwrap

import numpy as np
import pytest
from click.testing import CliRunner

from nehad.cli.main import main
from nehad.runtime.batch import BatchError, load_batch
from nehad.runtime.images import read_image
from nehad.runtime.video import probe_video
from video_model import build_tiny_export


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    return build_tiny_export(tmp_path_factory)


def write(tmp_path, text: str):
    p = tmp_path / "jobs.yaml"
    p.write_text(textwrap.dedent(text))
    return p


@pytest.mark.parametrize("body, message", [
    ("jobs:\n  - {name: a, model: m.onnx, output: a.mp4, fsp: 30}\n",
     "jobs.yaml: job 'a' (jobs[0]): fsp: unknown key; did you mean 'fps'?"),
    ("jobs:\n  - {model: m.onnx, output: a.mp4}\n  - {model: m.onnx, output: b.mp4, frames: -2}\n",
     "jobs.yaml: jobs[1]: frames: expected a whole number >= 1, got -2"),
    ("jobs:\n  - {name: s, model: m.onnx, output: s.png, frames: 3}\n",
     "jobs.yaml: job 's' (jobs[0]): frames: does not apply to an image job"),
    ("jobs:\n  - {name: v, output: v.mp4}\n",
     "jobs.yaml: job 'v' (jobs[0]): model: missing"),
    ("jobs:\n  - {name: v, model: m.onnx, output: v.avi}\n",
     "jobs.yaml: job 'v' (jobs[0]): output: v.avi: expected a .mp4 video or an image"),
    ("jobs:\n  - {name: v, model: m.onnx, output: v.mp4, size: 40}\n",
     "jobs.yaml: job 'v' (jobs[0]): size: expected WxH"),
    ("jobs:\n  - {name: v, model: m.onnx, output: v.mp4, time: 'a:b'}\n",
     "jobs.yaml: job 'v' (jobs[0]): time: a:b: expected a time T"),
    ("jobs:\n  - {name: v, model: m.onnx, output: v.mp4, background: [1, 1]}\n",
     "jobs.yaml: job 'v' (jobs[0]): background: expected [R, G, B]"),
    ("jobs:\n  - {name: v, model: m.onnx, output: v.mp4, side_by_side: 'yes'}\n",
     "jobs.yaml: job 'v' (jobs[0]): side_by_side: expected true or false"),
    ("jobs:\n  - {name: a, model: m.onnx, output: v.mp4}\n  - {name: b, model: m.onnx, output: v.mp4}\n",
     "jobs.yaml: job 'b' (jobs[1]): output: "),
    ("jobs:\n  - {name: a, model: m.onnx, output: a.mp4}\n  - {name: a, model: m.onnx, output: b.mp4}\n",
     "jobs.yaml: job 'a' (jobs[1]): name: 'a' is also the name of jobs[0]"),
    ("defaults: {fsp: 3}\njobs:\n  - {model: m.onnx, output: a.mp4}\n",
     "jobs.yaml: defaults: fsp: not a key defaults can set; did you mean 'fps'?"),
    ("job:\n  - {model: m.onnx, output: a.mp4}\n",
     "jobs.yaml: unknown top-level key 'job'; did you mean 'jobs'?"),
    ("jobs: []\n", "jobs.yaml: jobs: expected a non-empty list"),
    ("workers: 0\njobs:\n  - {model: m.onnx, output: a.mp4}\n",
     "jobs.yaml: workers: must be a whole number"),
    ("jobs:\n  - {model: m.onnx, output: a.mp4\n", "jobs.yaml: malformed YAML (line"),
])
def test_schema_errors_name_the_job_and_the_key(tmp_path, body, message):
    with pytest.raises(BatchError) as e:
        load_batch(write(tmp_path, body))
    expected = message.replace("jobs.yaml", str(tmp_path / "jobs.yaml"), 1)
    assert str(e.value).startswith(expected), str(e.value)
    assert "\n" not in str(e.value)


def test_defaults_relative_paths_and_types(tmp_path):
    spec = load_batch(write(tmp_path, """\
        workers: 2
        defaults: {model: m.onnx, size: [40, 32], fps: 24, frames: 5}
        jobs:
          - {name: a, output: out/a.mp4, path: "orbit:from=data,radius=2", time: [0, 0.5]}
          - {name: b, output: b.png, view: cams.json:1, time: 0.25}
          - {frames_dir: seq}
        """))
    a, b, c = spec.jobs
    assert spec.workers == 2 and [j.type for j in spec.jobs] == ["video", "image", "video"]
    assert a.settings["model"] == tmp_path / "m.onnx" and a.settings["size"] == (40, 32)
    assert a.settings["output"] == tmp_path / "out" / "a.mp4"
    assert a.settings["path"] == f"orbit:from={tmp_path / 'data'},radius=2"
    assert a.settings["time"] == "0.0:0.5" and a.settings["fps"] == 24.0
    assert b.settings["view"] == str(tmp_path / "cams.json:1") and "fps" not in b.settings
    assert c.name == "job3" and c.settings["frames_dir"] == tmp_path / "seq"


def test_cli_runs_every_job_and_reports_failures(model, tmp_path):
    onnx, scene = model
    (tmp_path / "out").mkdir()
    jobs = write(tmp_path, f"""\
        workers: 1
        defaults: {{model: {onnx}, size: 32x32}}
        jobs:
          - {{name: orbit, output: out/orbit.mp4, frames: 6, fps: 12}}
          - {{name: broken, model: missing.onnx, output: out/broken.mp4}}
          - {{name: still, output: out/still.png, view: {scene}/transforms_test.json:0}}
          - {{name: late, output: out/late.png, view: default, time: 3}}
          - {{name: seq, frames_dir: out/seq, frames: 3, time: 0.5}}
        """)
    res = CliRunner().invoke(main, ["batch", str(jobs), "--check"])  # what would fail, first
    assert res.exit_code == 1 and "(jobs[1]): model:" in res.stderr, res.output
    assert "missing.onnx: no such file or folder" in res.stderr
    res = CliRunner().invoke(main, ["batch", str(jobs), "--quiet"])
    assert res.exit_code == 1, res.output
    assert res.stderr.strip() == ("Error: 2 of 5 jobs failed: broken, late (each one's error is "
                                  "in the table above)"), res.stderr
    lines = res.stdout.strip().splitlines()
    assert lines[0].split()[:6] == ["job", "type", "frames", "rendered", "seconds", "status"]
    rows = {ln.split()[0]: ln for ln in lines[1:-1]}
    assert set(rows) == {"orbit", "broken", "still", "late", "seq"}
    assert " ok " in rows["orbit"] and str(tmp_path / "out" / "orbit.mp4") in rows["orbit"]
    assert "FAILED" in rows["broken"] and "missing.onnx: no such file" in rows["broken"]
    assert "FAILED" in rows["late"] and "time 3: time 3 is outside the trained time range [0, 1] (allow it with extrapolate: true)" in rows["late"]
    assert " ok " in rows["still"] and " ok " in rows["seq"]
    assert lines[-1] == "3 of 5 jobs done, 2 failed"
    info = probe_video(tmp_path / "out" / "orbit.mp4")
    assert (info["frames"], info["fps"], info["width"]) == (6, 12.0, 32)
    still = read_image(tmp_path / "out" / "still.png")
    assert still.shape == (32, 32, 3)
    # the same picture as `nehad render` of the same model, camera, time and size
    res = CliRunner().invoke(main, ["render", str(onnx), "--view",
                                    f"{scene}/transforms_test.json:0", "--size", "32x32",
                                    "-o", str(tmp_path / "ref.png")])
    assert res.exit_code == 0, res.output
    reference = read_image(tmp_path / "ref.png")
    assert reference.std() > 0.01  # not an empty picture
    np.testing.assert_array_equal(still, reference)
    assert len(list((tmp_path / "out" / "seq").glob("frame_*.png"))) == 3
    assert not (tmp_path / "out" / "broken.mp4").exists()
    # --resume: nothing left to render for the jobs that worked
    res = CliRunner().invoke(main, ["batch", str(jobs), "--quiet", "--resume"])
    rows = {ln.split()[0]: ln.split() for ln in res.output.strip().splitlines()[1:-1]}
    assert rows["seq"][3] == "0" and rows["still"][3] == "0" and rows["orbit"][3] == "0"


def test_cli_schema_error_is_one_line_and_runs_nothing(model, tmp_path):
    onnx, _ = model
    jobs = write(tmp_path, f"""\
        jobs:
          - {{name: good, model: {onnx}, output: good.mp4, frames: 2, size: 16x16}}
          - {{name: bad, model: {onnx}, output: bad.mp4, elevation: 30}}
        """)
    res = CliRunner().invoke(main, ["batch", str(jobs), "--quiet"])
    assert res.exit_code == 1
    assert res.output.startswith(f"Error: {jobs}: job 'bad' (jobs[1]): elevation: unknown key ")
    assert res.output.count("\n") == 1 and "Traceback" not in res.output
    assert not (tmp_path / "good.mp4").exists()
    assert CliRunner().invoke(main, ["batch", str(tmp_path / "none.yaml")]).output == \
        f"Error: {tmp_path / 'none.yaml'}: no such jobs file\n"
    res = CliRunner().invoke(main, ["batch", str(jobs), "--check"])
    assert res.exit_code == 1 and "elevation" in res.output
