"""Run directories and checkpoints (docs/design.md section 5): state dicts only, written atomically, loaded
with `weights_only=True`.

    RUN/config.yaml        the resolved config
    RUN/checkpoints/step_000500.pt
    RUN/model.pt           the final model (gaussians + field + what rendering needs)
    RUN/metrics.jsonl      one JSON object per log line

Reading is checked (issue 15): an empty, truncated, corrupt or foreign file raises
:class:`CheckpointError` naming the file and what is wrong with it, never torch's own advice to
load it with ``weights_only=False`` (which would run whatever code the file holds). The zip
archive's CRC-32 of every record is verified, so flipped bytes in the tensor data are refused
rather than loaded. Temporary files of the atomic writes name their writer, and those a killed
run left behind are removed by the next save or ``--resume`` (:mod:`nehad.runtime.tempfiles`).
"""

from __future__ import annotations

import json
import math
import os
import re
import time
import zipfile
from pathlib import Path

import torch

from nehad.runtime.errors import write_failure
from nehad.runtime.tempfiles import STALE_SECONDS, make_temp, remove_stale_temps

#: Keys every file of a run (checkpoint or model.pt) holds.
REQUIRED_KEYS = ("gaussians", "field", "config")
#: The `format` RUN/model.pt records (nehad.trainer.Trainer.model_state): the layout this
#: loader reads. A file that names another is refused; a checkpoint names none.
RUN_FORMAT = "nehad-run/1"
# temporary names of atomic_torch_save before issue 15: tempfile.mkstemp(prefix=".NAME.")
_OLD_TEMP = re.compile(r"^\.(step_\d+|model)\.pt\.[a-z0-9_]{8}$")


class CheckpointError(ValueError):
    """A checkpoint or model.pt that cannot be used (the message names the file)."""


class RunError(RuntimeError):
    """A run directory cannot be used as asked (e.g. resume with another config)."""


def prepare_run_dir(run: Path, cfg, resume: bool) -> None:
    """Make `run` ready for training with `cfg`: a new folder gets its config.yaml (atomically);
    an existing run is refused unless `resume`, and then only with the same config."""
    from nehad.configtools import diff, dump_yaml, load_yaml, to_dict

    cfg_path = run / "config.yaml"
    if cfg_path.exists():
        saved = load_yaml(cfg_path)  # a damaged config.yaml: one error naming it (issue 26)
        if not resume:
            raise RunError(f"{run}: already holds a run; pass --resume to continue it "
                           f"or choose another output folder")
        changes = diff(_with_defaults(saved), to_dict(cfg))
        if changes:
            raise RunError(f"{run}: --resume with a different config than the run's "
                           f"({'; '.join(changes[:6])}); use the same preset/--set values "
                           f"or another output folder")
    run.mkdir(parents=True, exist_ok=True)
    if not cfg_path.exists():
        from nehad.runtime.images import atomic_write_bytes
        atomic_write_bytes(cfg_path, dump_yaml(cfg).encode())


def _with_defaults(saved: dict) -> dict:
    """A saved config with the keys added to the project since it was written at their
    defaults (which is what the run trained with), so that resuming an older run is not refused
    for a key it never had; as saved if it no longer reads as a config."""
    from nehad.config import ConfigError, config_from_dict
    from nehad.configtools import to_dict

    try:
        return to_dict(config_from_dict(saved))
    except (ConfigError, TypeError, ValueError, KeyError):
        return saved


def atomic_torch_save(obj, path) -> Path:
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise write_failure(path.parent, e, "cannot create the folder") from None
    remove_stale_temps(path.parent)  # a killed save's leftovers, for any step (issue 15)
    try:
        tmp = make_temp(path)
    except OSError as e:
        raise write_failure(path, e, f"cannot create a file in {path.parent}") from None
    try:
        torch.save(obj, tmp)
        os.replace(tmp, path)
    except BaseException as e:
        if os.path.exists(tmp):
            os.unlink(tmp)
        # a full disk: OSError from the rename, torch's RuntimeError ("PytorchStreamWriter
        # failed writing file ...") from the archive writer
        if isinstance(e, OSError) or (isinstance(e, RuntimeError) and "writ" in str(e)):
            raise write_failure(path, e) from None
        raise
    return path


def remove_stale_run_temps(run) -> list[Path]:
    """Remove the temporary files a killed run left in RUN and RUN/checkpoints (``--resume``):
    stale ones of :mod:`nehad.runtime.tempfiles`' form, and the old-style ones (older than an
    hour)."""
    removed = []
    now = time.time()
    for folder in (Path(run), checkpoint_dir(run)):
        removed += remove_stale_temps(folder)
        if not folder.is_dir():
            continue
        for p in folder.iterdir():
            if _OLD_TEMP.match(p.name):
                try:
                    if now - p.lstat().st_mtime > STALE_SECONDS:
                        p.unlink()
                        removed.append(p)
                except OSError:
                    pass
    return removed


def _archive_problem(path: Path) -> str | None:
    """What is wrong with the file as a torch zip archive (None if nothing is)."""
    size = path.stat().st_size
    if size == 0:
        return "the file is empty"
    if not zipfile.is_zipfile(path):
        return "not a torch checkpoint archive (truncated or corrupt)"
    try:
        with zipfile.ZipFile(path) as z:
            bad = z.testzip()  # reads every record and checks its CRC-32
    except (zipfile.BadZipFile, OSError, EOFError, ValueError, NotImplementedError) as e:
        return f"not a readable archive ({' '.join(str(e).split())[:120]})"
    if bad is not None:
        return f"damaged: record {bad!r} does not match its checksum"
    return None


def load_state(path, resumable: bool = False) -> dict:
    """The state dict in `path` (a checkpoint or model.pt), checked: a readable, undamaged
    archive of tensors and plain values holding :data:`REQUIRED_KEYS` (and, with `resumable`,
    what a checkpoint adds to resume training from it); else CheckpointError."""
    path = Path(path)
    source = str(path)
    try:
        problem = _archive_problem(path)
    except FileNotFoundError:
        raise CheckpointError(f"{source}: no such file") from None
    except IsADirectoryError:
        raise CheckpointError(f"{source}: is a folder, not a checkpoint file") from None
    except OSError as e:
        raise CheckpointError(f"{source}: cannot read ({e.strerror or e})") from None
    if problem is not None:
        raise CheckpointError(f"{source}: {problem}; it cannot be used (train again, or resume "
                              f"from an intact checkpoint)")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except OSError as e:
        raise CheckpointError(f"{source}: cannot read ({e.strerror or type(e).__name__})") from None
    except Exception:
        # torch's message would suggest weights_only=False, i.e. running code from the file
        raise CheckpointError(f"{source}: holds something other than tensors and plain values "
                              f"(nehad writes state dicts only); refused") from None
    if not isinstance(state, dict):
        raise CheckpointError(f"{source}: not a nehad run file (holds a {type(state).__name__}, "
                              f"expected a state dict)")
    missing = [k for k in REQUIRED_KEYS if not isinstance(state.get(k), dict)]
    if missing:
        raise CheckpointError(f"{source}: not a nehad run file (lacks {', '.join(missing)})")
    if resumable:
        lacks = [k for k in ("optimizer", "strategy") if not isinstance(state.get(k), dict)]
        if lacks or not isinstance(state.get("step"), int):
            raise CheckpointError(f"{source}: not a training checkpoint (lacks "
                                  f"{', '.join(lacks or ['step'])}: a model.pt cannot be "
                                  f"resumed); remove it to resume from the one before")
    _check_contents(state, source)
    return state


def _check_contents(state: dict, source: str) -> None:
    """The Gaussians' tensors are all there, the field's values are tensors and the config is
    valid: what loading the model reads first (the rest is checked by load_state_dict)."""
    from nehad.config import config_from_dict
    from nehad.configtools import ConfigError
    from nehad.gaussians import GaussianParameters

    g = GaussianParameters.with_defaults(state["gaussians"])
    absent = [n for n in GaussianParameters.NAMES if not torch.is_tensor(g.get(n))]
    if absent:
        raise CheckpointError(f"{source}: not a nehad run file (its Gaussians lack "
                              f"{', '.join(absent)})")
    if not all(torch.is_tensor(v) for v in state["field"].values()):
        raise CheckpointError(f"{source}: not a nehad run file (its field holds non-tensors)")
    _check_gaussian_shapes(g, source)
    for part in ("gaussians", "field"):
        bad = [k for k, v in state[part].items()
               if v.is_floating_point() and not bool(torch.isfinite(v).all())]
        if bad:
            raise CheckpointError(f"{source}: its {part} hold NaN or infinite values "
                                  f"({', '.join(bad[:4])}); it cannot be used")
    _check_record(state, source)
    try:
        config_from_dict(state["config"])
    except (ConfigError, TypeError, ValueError) as e:
        raise CheckpointError(f"{source}: its config is invalid "
                              f"({' '.join(str(e).split())})") from None


def _row_shapes(shapes) -> str:
    """`(N, 3)`, `(N,) or (N, 1)`: the shapes a Gaussian tensor may have, for a message."""
    text = ["(" + ", ".join(["N"] + [str(d) for d in row]) + ("," if not row else "") + ")"
            for row in shapes]
    return " or ".join(text) if len(text) < 3 else ", ".join(text[:-1]) + " or " + text[-1]


def _check_gaussian_shapes(g: dict, source: str) -> None:
    """Every Gaussian tensor holds one row per Gaussian, of a shape
    `GaussianParameters.ROW_SHAPES` allows, all with the same number N > 0 of rows, and every
    quaternion is non-zero (a rotation is the quaternion divided by its length)."""
    from nehad.gaussians import GaussianParameters

    for name, rows in GaussianParameters.ROW_SHAPES.items():
        shape = tuple(g[name].shape)
        if not shape or shape[1:] not in rows:
            raise CheckpointError(f"{source}: its Gaussians' {name} has shape "
                                  f"{list(shape)}, expected {_row_shapes(rows)}")
    counts = {name: g[name].shape[0] for name in GaussianParameters.ROW_SHAPES}
    if len(set(counts.values())) > 1:
        raise CheckpointError(f"{source}: its Gaussian tensors have different numbers of rows ("
                              + ", ".join(f"{k} {v}" for k, v in counts.items()
                                          if k == "means" or v != counts["means"]) + ")")
    if counts["means"] == 0:
        raise CheckpointError(f"{source}: holds no Gaussians (0 rows); there is nothing to "
                              f"render")
    zero = torch.nonzero(g["quats"].norm(dim=-1) == 0).reshape(-1).tolist()
    if zero:
        raise CheckpointError(f"{source}: its Gaussians' quats are all zero in {len(zero)} "
                              f"rows ({', '.join(map(str, zero[:4]))}"
                              f"{', ...' if len(zero) > 4 else ''}): such a quaternion is no "
                              f"rotation")


def _check_record(state: dict, source: str) -> None:
    """The plain values a run records beside its tensors (nehad.model.RunInfo reads them):
    format :data:`RUN_FORMAT` or absent, sh_degree 0..3 or absent, background three numbers in
    [0, 1], time_range two finite numbers, the first not above the second, extent (the record's
    and the field's) a finite number above 0."""
    from nehad.data.common import DatasetError, vector

    def numbers(key, count):
        v = state.get(key)
        try:
            return vector(v.tolist() if torch.is_tensor(v) else v, count, source, key)
        except DatasetError as e:
            raise CheckpointError(str(e)) from None

    if state.get("format", RUN_FORMAT) != RUN_FORMAT:
        raise CheckpointError(f"{source}: its format is {state['format']!r}, not "
                              f"{RUN_FORMAT!r} (the one this nehad reads)")

    degree = state.get("sh_degree")
    if degree is not None and (isinstance(degree, bool) or degree not in (0, 1, 2, 3)):
        raise CheckpointError(f"{source}: its sh_degree must be 0, 1, 2 or 3, got {degree!r}")
    if state.get("background") is not None and not all(
            0.0 <= c <= 1.0 for c in numbers("background", 3)):
        raise CheckpointError(f"{source}: its background must lie in [0, 1], "
                              f"got {state['background']!r}")
    if state.get("time_range") is not None:
        lo, hi = numbers("time_range", 2)
        if lo > hi:
            raise CheckpointError(f"{source}: its time_range must not decrease, got [{lo}, {hi}]")
    for part, value in (("extent", state.get("extent")),
                        ("field's extent", state["field"].get("extent"))):
        number = value.item() if torch.is_tensor(value) and value.numel() == 1 else value
        if value is not None and (isinstance(number, bool) or not isinstance(number, (int, float))
                                  or not math.isfinite(number) or number <= 0):
            raise CheckpointError(f"{source}: its {part} must be a finite number above 0, "
                                  f"got {number!r}")


def checkpoint_dir(run: Path) -> Path:
    return Path(run) / "checkpoints"


def list_checkpoints(run: Path) -> list[Path]:
    d = checkpoint_dir(run)
    return sorted(d.glob("step_*.pt")) if d.is_dir() else []


def save_checkpoint(run: Path, step: int, state: dict, keep: int) -> Path:
    path = atomic_torch_save(state, checkpoint_dir(run) / f"step_{step:07d}.pt")
    for old in list_checkpoints(run)[:-max(keep, 1)]:
        old.unlink(missing_ok=True)
    return path


# The last step this process appended to each metrics file (see append_metrics).
_LAST_LOGGED: dict[str, int] = {}


def _drop_records_from(path: Path, step: int | None) -> None:
    """Rewrite `path` (atomically) without the records of `step` and later, and without a torn
    last line; leave it alone when there is nothing to drop."""
    from nehad.runtime.images import atomic_write_bytes

    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except FileNotFoundError:
        return
    keep, dropped = [], False
    for line in text.splitlines():
        try:
            rec = json.loads(line)
        except ValueError:
            dropped = True
            continue
        s = rec.get("step") if isinstance(rec, dict) else None
        if step is not None and isinstance(s, (int, float)) and s >= step:
            dropped = True
            continue
        keep.append(line)
    if dropped or (text and not text.endswith("\n")):
        atomic_write_bytes(path, "".join(line + "\n" for line in keep).encode("utf-8"))


def append_metrics(run: Path, record: dict) -> None:
    """Append one record to RUN/metrics.jsonl.

    A resumed run repeats the steps between its checkpoint and the moment the earlier run
    stopped; their records from the earlier run are dropped when the first record of the
    repeat arrives (any record with a step at or after it), so every step is logged once. A
    torn last line (a kill during the append) is dropped at the same time."""
    path = Path(run) / "metrics.jsonl"
    key = str(path.absolute())
    step = record.get("step")
    last = _LAST_LOGGED.get(key)
    if last is None or not isinstance(step, int) or step <= last:
        _drop_records_from(path, step if isinstance(step, int) else None)
    try:
        with open(path, "a") as f:
            f.write(json.dumps(record) + "\n")
    except OSError as e:
        raise write_failure(path, e, "cannot append to it") from None
    if isinstance(step, int):
        _LAST_LOGGED[key] = step
