"""Per-object scores of `nehad eval` (issue 25): PSNR on each labelled object's ground-truth
pixels beside a blank image's, per time quarter, the mask downscale rule, and the warning line of
an object that is not drawn. Fast: no training (the last test fakes the model's renders)."""

from __future__ import annotations

import dataclasses
import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("torch")
cv2 = pytest.importorskip("cv2")

from nehad import evaluate  # noqa: E402
from nehad.evaluate import (object_errors, object_label_map, object_warnings,  # noqa: E402
                            summarize_objects, worst_object_bin)

RED, WHITE = (1.0, 0.0, 0.0), (1.0, 1.0, 1.0)


# ------------------------------------------------------------------------------------------
# the score against a hand-computed case


def test_object_psnr_hand_computed():
    """Two frames in the first quarter, one in the third; white background.

    Object 1 (red) in frame A (t 0.10): one pixel rendered (0.7, 0, 0): squared error per
    channel 0.09, 0, 0 -> 0.03 mean over RGB. In frame B (t 0.20): three pixels drawn exactly.
    Pooled over the quarter's 4 pixels: MSE 0.03 / 4 = 0.0075 -> PSNR 10 log10(1 / 0.0075) =
    21.249 dB (a mean of per-frame PSNRs would be (15.23 + 100) / 2 instead).
    Blank (white) on a red pixel: (0 + 1 + 1) / 3 = 2/3 -> 10 log10(1.5) = 1.761 dB.
    Object 2 (grey 0.5) in frame C (t 0.60), 2 pixels, rendered white (not drawn): error
    0.25 on every channel -> 6.021 dB, blank the same -> gain 0.
    """
    bg = np.array(WHITE)
    # frame A: 2x3, object 1 at (0, 0); the rest background
    truth_a = np.ones((2, 3, 3))
    truth_a[0, 0] = RED
    render_a = truth_a.copy()
    render_a[0, 0] = (0.7, 0.0, 0.0)
    labels_a = np.array([[1, 0, 0], [0, 0, 0]])
    # frame B: object 1 on three pixels, drawn exactly
    truth_b = np.ones((2, 3, 3))
    labels_b = np.array([[1, 1, 0], [0, 1, 0]])
    truth_b[labels_b == 1] = RED
    render_b = truth_b.copy()
    # frame C: object 2 (grey) on two pixels, render all white
    truth_c = np.ones((2, 3, 3))
    labels_c = np.array([[0, 0, 0], [0, 2, 2]])
    truth_c[labels_c == 2] = 0.5
    render_c = np.ones((2, 3, 3))

    records = []
    for t, lab, r, g in ((0.10, labels_a, render_a, truth_a), (0.20, labels_b, render_b, truth_b),
                         (0.60, labels_c, render_c, truth_c)):
        records.append({"time": t, "ids": sorted(set(np.unique(lab)) - {0}),
                        "errors": object_errors(lab, r, g, bg)})
    assert records[0]["errors"][1] == (1, pytest.approx(0.03), pytest.approx(2 / 3))

    objects = summarize_objects(records, {1: "red", 2: "grey"}, (0.0, 1.0), min_pixels=1)
    assert [o["name"] for o in objects] == ["red", "grey"]
    red, grey = objects
    q1 = red["time_bins"][0]
    assert q1["range"] == [0.0, 0.25] and q1["frames"] == 2 and q1["pixels"] == 4
    assert q1["psnr"] == pytest.approx(21.2494, abs=1e-3)
    assert q1["blank_psnr"] == pytest.approx(1.7609, abs=1e-3)
    assert q1["gain"] == pytest.approx(19.4885, abs=1e-3)
    # the third quarter holds a frame but no red pixel: listed, not scored
    q3 = red["time_bins"][1]
    assert q3["range"] == [0.5, 0.75] and q3["pixels"] == 0 and q3["psnr"] is None
    assert "skipped" in q3
    # overall = the same 4 pixels
    assert red["psnr"] == pytest.approx(21.2494, abs=1e-3) and red["pixels"] == 4
    g3 = grey["time_bins"][1]
    assert g3["psnr"] == pytest.approx(6.0206, abs=1e-3)
    assert g3["blank_psnr"] == pytest.approx(6.0206, abs=1e-3) and abs(g3["gain"]) < 1e-9
    assert grey["time_bins"][0]["psnr"] is None  # no grey pixel in the first quarter
    worst = worst_object_bin(objects)
    assert worst["name"] == "grey" and worst["range"] == [0.5, 0.75]


def test_unlabelled_foreground_hand_computed():
    """The opaque pixels no label covers (a floor, its shadows): label 0 where alpha >= 0.5.

    2x3 frame, labels [[1, 0, 0], [0, 0, 0]], alpha [[1, 1, 0.2], [0.6, 0, 0.5]]: the unlabelled
    foreground is (0, 1), (1, 0) and (1, 2) (alpha 0.5 counts, 0.2 does not; (0, 0) is the
    object's). Truth there grey 0.5; the render draws (0, 1) and (1, 2) exactly and leaves (1, 0)
    white: squared error 0.25 on one pixel; the white blank 0.25 on all three."""
    bg = np.array(WHITE)
    labels = np.array([[1, 0, 0], [0, 0, 0]])
    alpha = np.array([[1.0, 1.0, 0.2], [0.6, 0.0, 0.5]])
    truth = np.ones((2, 3, 3))
    truth[0, 0] = RED
    for r, c in ((0, 1), (1, 0), (1, 2)):
        truth[r, c] = 0.5
    render = truth.copy()
    render[1, 0] = 1.0
    render[0, 2] = 0.0  # wrong, but transparent in the target: not scored here
    pixels, sse, bsse = evaluate.unlabelled_errors(labels, alpha, render, truth, bg)
    assert pixels == 3 and sse == pytest.approx(0.25) and bsse == pytest.approx(0.75)


def test_too_few_pixels_skip_a_quarter():
    bg = np.array(WHITE)
    lab = np.zeros((4, 4), int)
    lab[0, :3] = 1
    truth = np.ones((4, 4, 3))
    truth[lab == 1] = RED
    rec = [{"time": 0.1, "ids": [1], "errors": object_errors(lab, truth, truth, bg)}]
    assert summarize_objects(rec, {}, (0, 1), min_pixels=4)[0]["time_bins"][0]["psnr"] is None
    obj = summarize_objects(rec, {}, (0, 1), min_pixels=3)[0]
    assert obj["name"] == "object 1"
    assert obj["time_bins"][0]["psnr"] == evaluate.PSNR_CAP  # zero error


# ------------------------------------------------------------------------------------------
# the mask downscale rule


def test_mask_downscale_rule():
    """2x2 blocks: an object's pixel needs >= half its block; ties go to the lower id."""
    lab = np.array([[1, 1, 1, 0, 2, 2],
                    [0, 0, 0, 0, 1, 1],
                    [2, 2, 2, 0, 0, 0],
                    [2, 0, 0, 0, 0, 3]])
    got = object_label_map(lab, 3, 2)
    # blocks: [1,1,0,0] -> 1 (1/2); [1,0,0,0] -> 0 (1/4); [2,2,1,1] -> 1 (tie, lower id)
    #         [2,2,2,0] -> 2 (3/4); [2,0,0,0] -> 0; [0,0,0,3] -> 0
    assert got.tolist() == [[1, 0, 1], [2, 0, 0]]
    # a remainder at the right/bottom is cropped, as the image loader does
    odd = np.zeros((5, 7), int)
    odd[:2, :2] = 4
    odd[4, :] = 5
    odd[:, 6] = 5
    assert object_label_map(odd, 3, 2).tolist() == [[4, 0, 0], [0, 0, 0]]
    # factor 1 is the mask itself
    assert object_label_map(lab, 6, 4).tolist() == lab.tolist()
    with pytest.raises(ValueError, match="integer downscale"):
        object_label_map(lab, 4, 2)


# ------------------------------------------------------------------------------------------
# the warning line


def _obj(name, gains):
    bins = [{"range": [k / 4, (k + 1) / 4], "frames": 2, "pixels": 0 if g is None else 50,
             "psnr": None if g is None else 20 + g, "blank_psnr": None if g is None else 20.0,
             "gain": g} for k, g in enumerate(gains)]
    return {"id": 1, "name": name, "psnr": 30.0, "blank_psnr": 20.0, "gain": 10.0,
            "time_bins": bins}


def test_warning_lines():
    objs = [_obj("sphere_red", [0.4, 12.0, None, 9.0]), _obj("cube", [10.0, 3.0, 8.0, 4.0]),
            _obj("rod", [2.99, -1.25, 5.0, 5.0])]
    assert object_warnings(objs) == [
        "warning: sphere_red missing in t 0.00-0.25 (+0.4 dB over blank on its pixels)",
        "warning: rod missing in t 0.00-0.25, t 0.25-0.50 (+3.0, -1.2 dB over blank on its "
        "pixels)"]
    # the threshold is a parameter; a result dict works as well as the list
    assert object_warnings({"objects": objs}, threshold=0.0) == [
        "warning: rod missing in t 0.25-0.50 (-1.2 dB over blank on its pixels)"]
    assert object_warnings({}) == []


# ------------------------------------------------------------------------------------------
# a missing object is flagged, through `nehad eval` on a dataset with label masks


def _write_dataset(root, n=8, size=16):
    """A D-NeRF folder with RGBA images over a transparent background, `test/masks` label
    masks and class_mapping.json: a red square (id 1) and a blue one (id 2) moving."""
    (root / "test" / "masks").mkdir(parents=True)
    frames = []
    for k in range(n):
        lab = np.zeros((size, size), np.uint8)
        lab[2:10, k:k + 8] = 1  # 8x8, moves right
        lab[10:16, 8 - k // 2:14 - k // 2] = 2  # 6x6
        rgba = np.zeros((size, size, 4), np.uint8)  # BGRA for OpenCV
        rgba[lab == 1] = (0, 0, 255, 255)
        rgba[lab == 2] = (255, 0, 0, 255)
        rgba[0:2] = (128, 128, 128, 255)  # an unlabelled grey floor strip
        cv2.imwrite(str(root / "test" / f"r_{k:04d}.png"), rgba)
        cv2.imwrite(str(root / "test" / "masks" / f"r_{k:04d}.png"), lab)
        frames.append({"file_path": f"./test/r_{k:04d}", "time": k / (n - 1),
                       "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4],
                                            [0, 0, 0, 1]]})
    (root / "transforms_test.json").write_text(json.dumps({"camera_angle_x": 0.7,
                                                           "frames": frames}))
    (root / "class_mapping.json").write_text(json.dumps({"0": "background", "1": "box_red",
                                                         "2": "box_blue"}))


def test_missing_object_is_flagged(tmp_path, monkeypatch):
    """A model that draws everything except the blue box before t = 0.25: the eval names it in
    a warning (CLI output, metrics.json); the red box, always drawn, is not named."""
    from click.testing import CliRunner

    import nehad.runtime.raster as raster
    from nehad.cli.main import main
    from nehad.config import build_config
    from nehad.data.dnerf import load_dnerf

    data, run = tmp_path / "data", tmp_path / "run"
    _write_dataset(data)
    run.mkdir()
    (run / "model.pt").write_bytes(b"")  # the CLI checks that the file exists
    cfg = build_config("test", None, ["data.downscale=2"])
    from nehad.model import RunInfo

    meta = RunInfo(config_dict=dataclasses.asdict(cfg), background=(1.0, 1.0, 1.0), sh_degree=0,
                   time_range=(0.0, 1.0), data_dir=str(data))
    truth = {f.camera.time: f for f in load_dnerf(data, ("test",), downscale=2).frames["test"]}

    def fake_render(t, camera, background):
        f = truth[t]
        rgb = np.clip(f.image + 0.01, 0, 1)  # drawn, 40 dB on the red box
        if t < 0.25:  # the blue box is not drawn: background where it should be
            blue = f.image[:, :, 2] > f.image[:, :, 0] + 0.2
            rgb[blue] = 1.0
        if t > 0.75:  # nor the unlabelled floor strip: scored, but never a warning
            rgb[0] = 1.0
        return SimpleNamespace(rgb=rgb.astype(np.float32))

    monkeypatch.setattr(evaluate, "load_run", lambda r: (SimpleNamespace(gaussians=[0] * 7),
                                                         meta))
    monkeypatch.setattr(evaluate, "cloud_at", lambda model, t, degree: t)
    monkeypatch.setattr(raster, "render", fake_render)

    res = CliRunner().invoke(main, ["eval", str(run), "--quiet", "--no-lpips"])
    assert res.exit_code == 0, res.output
    out = json.loads((run / "eval_test" / "metrics.json").read_text())
    assert out["resolution"] == [8, 8]
    names = {o["name"]: o for o in out["objects"]}
    assert set(names) == {"box_red", "box_blue"}
    blue, red = names["box_blue"], names["box_red"]
    assert [tb["frames"] for tb in blue["time_bins"]] == [2, 2, 2, 2]
    assert blue["time_bins"][0]["gain"] == pytest.approx(0.0, abs=1e-6)
    assert all(tb["gain"] > 15 for tb in blue["time_bins"][1:])
    assert all(tb["gain"] > 15 for tb in red["time_bins"])
    # 8x8 red square at 2x: 16 pixels per frame (its odd offsets give 12 whole + 8 half blocks)
    assert all(tb["pixels"] >= 2 * 12 for tb in red["time_bins"])
    assert out["worst_object_bin"]["name"] == "box_blue"
    assert out["worst_object_bin"]["range"] == [0.0, 0.25]
    warning = "warning: box_blue missing in t 0.00-0.25 (+0.0 dB over blank on its pixels)"
    assert out["object_warnings"] == [warning]
    # per frame: frame 0's red square covers whole 2x2 blocks (16 pixels of truth (1, 0, 0));
    # the render adds 0.01 to G and B (R clips at 1): mean squared error 2e-4 / 3 against the
    # white blank's 2 / 3, a gain of exactly 10 log10(1e4) = 40 dB
    frame0 = out["per_frame"][0]["objects"]
    assert frame0["box_red"]["pixels"] == 16
    assert frame0["box_red"]["gain"] == pytest.approx(40.0, abs=1e-3)
    for rec in out["per_frame"]:  # the blue box undrawn before 0.25, drawn after
        gain = rec["objects"]["box_blue"]["gain"]
        assert gain == pytest.approx(0.0, abs=1e-6) if rec["time"] < 0.25 else gain > 15
    for tb in blue["time_bins"] + red["time_bins"]:  # the frames' errors pool to the quarter's
        name = "box_blue" if tb in blue["time_bins"] else "box_red"
        lo, hi = tb["range"]
        recs = [r["objects"][name] for r in out["per_frame"]
                if lo <= r["time"] < hi or (hi == 1.0 and r["time"] == 1.0)]
        pixels = sum(o["pixels"] for o in recs)
        sse = sum(o["pixels"] * 10 ** (-o["psnr"] / 10) for o in recs)
        assert pixels == tb["pixels"]
        assert 10 * math.log10(pixels / sse) == pytest.approx(tb["psnr"], abs=1e-6)
    floor = out["unlabelled"]  # the grey strip: one 8-pixel row per frame at 2x
    assert floor["name"] == "unlabelled foreground"
    assert [tb["pixels"] for tb in floor["time_bins"]] == [16, 16, 16, 16]
    assert all(tb["gain"] > 15 for tb in floor["time_bins"][:3])
    assert floor["time_bins"][3]["gain"] == pytest.approx(0.0, abs=1e-6)
    lines = res.output.rstrip("\n").splitlines()
    assert lines[-1] == warning  # printed last, after "wrote ... metrics.json"
    assert "box_red" not in "\n".join(lines[-2:])
    table = evaluate.format_table(out)
    assert "Objects:" in table and table.splitlines()[-1] == warning
    assert "+0.0!" in table and table.count("!") == 2  # the blue box's cell and the legend
    assert "unlabelled foreground" in table
    assert not math.isnan(red["psnr"])


def _eval_without_a_model(tmp_path, monkeypatch):
    """(dataset, run, result of `nehad eval RUN`) for _write_dataset's scene, with the run's
    model faked (every render is the ground truth), as test_missing_object_is_flagged does;
    the dataset's files may be changed before calling the returned function."""
    from click.testing import CliRunner

    import nehad.runtime.raster as raster
    from nehad.cli.main import main
    from nehad.config import build_config
    from nehad.model import RunInfo

    data, run = tmp_path / "data", tmp_path / "run"
    _write_dataset(data)
    run.mkdir()
    (run / "model.pt").write_bytes(b"")  # the CLI checks that the file exists
    meta = RunInfo(config_dict=dataclasses.asdict(build_config("test", None, [])),
                   background=(1.0, 1.0, 1.0), sh_degree=0, time_range=(0.0, 1.0),
                   data_dir=str(data))
    monkeypatch.setattr(evaluate, "load_run", lambda r: (SimpleNamespace(gaussians=[0] * 7),
                                                         meta))
    monkeypatch.setattr(evaluate, "cloud_at", lambda model, t, degree: t)
    monkeypatch.setattr(raster, "render", lambda t, camera, background: SimpleNamespace(
        rgb=np.full((camera.height, camera.width, 3), 0.5, np.float32)))
    return data, run, lambda: CliRunner().invoke(main, ["eval", str(run), "--quiet",
                                                        "--no-lpips"])


def test_bad_mask_is_refused_before_any_render(tmp_path, monkeypatch):
    """An unreadable label mask (the last frame's) ends the eval with one line naming it, before
    any frame is rendered: no RUN/eval_test/r_000.png is left behind."""
    from clean_errors import one_error

    data, run, invoke = _eval_without_a_model(tmp_path, monkeypatch)
    mask = data / "test" / "masks" / "r_0007.png"
    mask.write_bytes(b"not a png")
    one_error(invoke(), str(mask), "cannot read the label mask")
    assert sorted(p.name for p in run.iterdir()) == ["model.pt"]


def test_empty_masks_folder_is_refused(tmp_path, monkeypatch):
    """A masks folder without a mask beside class_mapping.json is an error naming the folder
    (silently scoring no objects would hide them); the eval runs once the masks are back."""
    from clean_errors import one_error

    data, run, invoke = _eval_without_a_model(tmp_path, monkeypatch)
    folder = data / "test" / "masks"
    kept = tmp_path / "kept"
    folder.rename(kept)
    folder.mkdir()
    one_error(invoke(), str(folder), "holds no label masks", "class_mapping.json")
    assert sorted(p.name for p in run.iterdir()) == ["model.pt"]
    folder.rmdir()
    kept.rename(folder)
    res = invoke()
    assert res.exit_code == 0, res.output
    assert json.loads((run / "eval_test" / "metrics.json").read_text())["objects"]


def test_report_shows_objects_and_warnings(tmp_path):
    from nehad.viz.report import metrics_section

    objs = [_obj("sphere_red", [0.4, 12.0, None, 9.0]), _obj("cube", [10.0, 8.0, 8.0, 4.0])]
    result = {"split": "test", "frames": 8, "resolution": [8, 8], "mean": {}, "objects": objs,
              "object_warnings": object_warnings(objs),
              "object_rules": {"min_pixels": 16, "warn_gain_db": 3.0},
              "unlabelled": _obj("unlabelled foreground", [0.2, 5.0, 5.0, 5.0])}
    (tmp_path / "eval_test").mkdir()
    (tmp_path / "eval_test" / "metrics.json").write_text(json.dumps(result))
    page = metrics_section(tmp_path)
    assert page.count('class="warn"') == 1
    assert "sphere_red missing in t 0.00-0.25" in page
    assert page.count('class="bad"') == 1  # the +0.4 cell only, not the floor's +0.2
    assert ">unlabelled foreground</td>" in page and ">+0.20</td>" in page
    assert ">+0.40</td>" in page and "n/a (" in page  # the skipped quarter
    assert page.index("<table>") < page.index("Objects (test)")  # after the metrics table
    # no objects in the file: no object table
    (tmp_path / "eval_test" / "metrics.json").write_text(json.dumps({"split": "test"}))
    assert "Objects" not in metrics_section(tmp_path)
