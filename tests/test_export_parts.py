"""An exported file in parts, deformed side by side by the runtime (docs/design.md section 7,
issue 27): the part outputs are rows of the whole ones, the whole outputs are those of a file
without parts, the runtime's side-by-side sessions give what one session gives, and the graph
cut down to some outputs keeps exactly the nodes they depend on."""

from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")

from click.testing import CliRunner  # noqa: E402

from nehad.cli.main import main  # noqa: E402
from nehad.export.graph import part_bounds  # noqa: E402
from nehad.runtime.onnx_model import OnnxModel, OnnxModelError  # noqa: E402
from nehad.runtime.onnx_proto import ProtoError, graph_for_outputs  # noqa: E402

OUTPUTS = ("means", "scales", "quats", "opacities", "sh")
TIMES = (0.0, 0.31, 0.77, 1.0)


def test_part_bounds_share_out_the_moving_gaussians():
    rng = np.random.default_rng(0)
    moving = rng.random(1000) < 0.4
    moving[:300] = False  # a still stretch: the first part takes it whole
    m = int(moving.sum())
    b = part_bounds(moving, 4, min_rows=10)
    assert len(b) == 5 and b[0] == 0 and b[-1] == 1000
    assert all(x < y for x, y in zip(b[:-1], b[1:]))
    counts = [int(moving[x:y].sum()) for x, y in zip(b[:-1], b[1:])]
    assert sum(counts) == m and max(counts) - min(counts) <= 1, counts
    assert len(part_bounds(moving, 4, min_rows=m // 2)) == 3  # 2 parts of >= m / 2
    assert part_bounds(moving, 4, min_rows=m // 2 + 1) == [0, 1000]
    assert part_bounds(np.zeros(50, bool), 4, min_rows=1) == [0, 50]
    assert part_bounds(moving, 1, min_rows=1) == [0, 1000]


@pytest.fixture(scope="module")
def two_files(tmp_path_factory):
    """(file without parts, file in 3 parts) of one tiny trained HNN run."""
    from test_export import make_run

    from nehad.export.onnx_export import export_run

    root = tmp_path_factory.mktemp("parts")
    run, _ = make_run(root, "hnn", seed=5)
    whole, parted = root / "whole.onnx", root / "parts.onnx"
    export_run(run, whole, parts=1)
    rep = export_run(run, parted, parts=3, min_part_rows=1)
    assert "parts" not in OnnxModel(whole, threads=1).metadata
    return whole, parted, json.loads(rep.metadata["parts"])


def _session_outputs(path, t, names=None):
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    names = names or [o.name for o in sess.get_outputs()]
    return dict(zip(names, sess.run(names, {"time": np.array([t], np.float32)})))


def test_parts_are_rows_of_the_whole_and_the_whole_is_unchanged(two_files):
    whole, parted, bounds = two_files
    assert len(bounds) == 4 and bounds[0] == 0
    for t in TIMES:
        ref, got = _session_outputs(whole, t), _session_outputs(parted, t)
        for name in OUTPUTS:
            np.testing.assert_allclose(got[name], ref[name], rtol=1e-6, atol=1e-6)
        for p in range(3):
            a, b = bounds[p], bounds[p + 1]
            for name in ("means", "scales", "quats", "opacities"):  # SH: a constant, whole
                np.testing.assert_array_equal(got[f"{name}.part{p}"], got[name][a:b])
        assert "sh.part0" not in got  # the field does not deform SH in this run


def test_the_runtime_deforms_the_parts_side_by_side(two_files):
    whole, parted, _ = two_files
    side = OnnxModel(parted, threads=2, cache_size=0)
    one = OnnxModel(parted, threads=1, cache_size=0)
    ref = OnnxModel(whole, threads=1, cache_size=0)
    assert side.workers == 2 and side.session is None and len(side._part_sessions) == 2
    assert one.workers == 1 and one.session is None and len(one._part_sessions) == 1
    assert ref.workers == 1 and ref.session is not None and not ref._part_sessions
    for t in TIMES + (0.31,):  # twice at one time: the constants fetched once, then reused
        a, b, c = side.outputs(t), one.outputs(t), ref.outputs(t)
        assert list(a) == list(b) == list(c) == list(OUTPUTS)
        for name in OUTPUTS:
            np.testing.assert_array_equal(a[name], b[name])
            np.testing.assert_allclose(a[name], c[name], rtol=1e-6, atol=1e-6)
    res = CliRunner().invoke(main, ["info", str(parted)])
    assert res.exit_code == 0 and "parts:        3" in res.output, res.output


def _reachable(model, names):
    """Node names and initializer names `names` depend on, by the onnx package's own graph."""
    made_by = {o: n for n in model.graph.node for o in n.output}
    nodes, values, stack = set(), set(names), list(names)
    while stack:
        node = made_by.get(stack.pop())
        if node is None or node.name in nodes:
            continue
        nodes.add(node.name)
        for i in node.input:
            if i and i not in values:
                values.add(i)
                stack.append(i)
    inits = {i.name for i in model.graph.initializer} & values
    return nodes, inits


def test_graph_for_outputs_keeps_exactly_what_computes_them(two_files):
    _, parted, _ = two_files
    keep = ["means.part1", "opacities.part2"]
    data = parted.read_bytes()
    cut = onnx.load_from_string(graph_for_outputs(data, keep))
    onnx.checker.check_model(cut, full_check=True)
    full = onnx.load_from_string(data)
    nodes, inits = _reachable(full, keep)
    assert {n.name for n in cut.graph.node} == nodes
    assert len(nodes) < len(full.graph.node) / 2  # two of the three parts' nodes are gone
    assert {i.name for i in cut.graph.initializer} == inits
    assert [o.name for o in cut.graph.output] == keep
    assert {p.key: p.value for p in cut.metadata_props} == \
        {p.key: p.value for p in full.metadata_props}
    sess = ort.InferenceSession(cut.SerializeToString(), providers=["CPUExecutionProvider"])
    ref = _session_outputs(parted, 0.4)
    for name, value in zip(keep, sess.run(keep, {"time": np.array([0.4], np.float32)})):
        np.testing.assert_array_equal(value, ref[name])
    with pytest.raises(ProtoError, match="no outputs"):
        graph_for_outputs(data, ["means.part9"])


def test_bad_parts_metadata_is_refused(tmp_path):
    from test_runtime_onnx import fake_model

    cases = {"range": ("[0, 5]", "must increase from 0 to num_gaussians 2"),
             "order": ("[0, 2, 1, 2]", "must increase from 0"),
             "text": ("[0, \"2\"]", "must be a list of row numbers"),
             "deep": ("[" * 100000, "not valid JSON"),
             "outputs": ("[0, 1, 2]", "no part outputs")}
    for name, (value, needle) in cases.items():
        path = fake_model(tmp_path / f"{name}.onnx", metadata={"parts": value})
        with pytest.raises(OnnxModelError, match=needle) as e:
            OnnxModel(path, threads=2)
        assert str(path) in str(e.value)


def _edited(src, dst, edit):
    """`src` with `edit(graph)` applied and its graph digest written anew (a crafted file that
    passes the integrity check)."""
    from nehad.runtime.onnx_proto import graph_sha256

    model = onnx.load(str(src))
    edit(model.graph)
    digest = graph_sha256(model.SerializeToString())
    for prop in model.metadata_props:
        if prop.key == "graph_sha256":
            prop.value = digest
    onnx.save(model, str(dst))
    return dst


def test_crafted_files_in_parts(two_files, tmp_path):
    """The review's cases: outputs listed in another order still give the right rows; a file
    whose moving outputs lack parts, or whose output without parts reads the time, is refused;
    initializers that are also graph inputs (overridable) do not become required inputs of a
    part's cut graph."""
    _, parted, _ = two_files
    ref = OnnxModel(parted, threads=1, cache_size=0).outputs(0.6)

    def reverse(graph):
        outs = list(graph.output)[::-1]
        del graph.output[:]
        graph.output.extend(outs)

    def as_inputs(graph):
        graph.input.extend(onnx.helper.make_tensor_value_info(
            i.name, i.data_type, list(i.dims)) for i in graph.initializer)

    for name, edit in (("reversed", reverse), ("inputs", as_inputs)):
        path = _edited(parted, tmp_path / f"{name}.onnx", edit)
        got = OnnxModel(path, threads=2, cache_size=0).outputs(0.6)
        for key in OUTPUTS:
            np.testing.assert_array_equal(got[key], ref[key])

    def drop(prefix):
        def edit(graph):
            keep = [o for o in graph.output if not o.name.startswith(prefix)]
            del graph.output[:]
            graph.output.extend(keep)
        return edit

    def sh_from_time(graph):  # sh = its constant + 0 * time: the "constant" reads the time
        for node in graph.node:
            node.output[:] = ["sh_c" if x == "sh" else x for x in node.output]
        graph.node.extend([onnx.helper.make_node("Sub", ["time", "time"], ["zero_t"]),
                           onnx.helper.make_node("Add", ["sh_c", "zero_t"], ["sh"])])

    for name, edit, needle in (("nomeans", drop("means.part"), "have no part outputs"),
                               ("shtime", sh_from_time, "read the inputs \\['time'\\]")):
        path = _edited(parted, tmp_path / f"{name}.onnx", edit)
        onnx.checker.check_model(onnx.load(str(path)), full_check=True)
        with pytest.raises(OnnxModelError, match=needle) as e:
            OnnxModel(path, threads=2)
        assert str(path) in str(e.value)


@pytest.mark.parametrize("extra,fp16", [(("field.mipmap=true",), False), ((), True)])
def test_parts_with_mipmapping_and_fp16_weights(tmp_path, extra, fp16):
    """The mipmapped spatial features stored for every row are looked up by each part's rows
    (`FastDeform(rows=)`), and fp16 weights are shared by the parts: the export's own parity
    check (1e-5 against the torch model) holds, and the parts side by side give the rows of one
    thread's run."""
    from test_export import make_run

    from nehad.export.onnx_export import export_run

    run, _ = make_run(tmp_path, "hnn", seed=2, extra=extra)
    path = tmp_path / "m.onnx"
    rep = export_run(run, path, parts=3, min_part_rows=1, fp16_weights=fp16)
    assert len(json.loads(rep.metadata["parts"])) == 4 and max(rep.parity.values()) <= 1e-5
    side, one = OnnxModel(path, threads=2, cache_size=0), OnnxModel(path, threads=1)
    for t in (0.1, 0.9):
        a, b = side.outputs(t), one.outputs(t)
        for name in OUTPUTS:
            np.testing.assert_array_equal(a[name], b[name])
