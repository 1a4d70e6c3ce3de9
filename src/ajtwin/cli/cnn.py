"""``ajtwin cnn`` — height-profile CNN: data, training, cross-validation, Q_m inference.

The default model is reproduced by one command (no weights are shipped)::

    ajtwin cnn train --synthetic --seed 0 --out model.pt

(125 synthetic profilometer pairs + 4000 CV-labelled columns rendered by the
vision module; the recipe of ``data/profile_cnn.toml`` [training]: the 1-D U-Net,
stage 1 then 50 epochs of stage 2, best of 8 restarts by a validation split).
"""

from __future__ import annotations

import functools
import json
from pathlib import Path

import click

from ajtwin.cli.options import join_options
from ajtwin.io.records import PrintRecord, RecordError, read_record, write_record

_SMOOTHING_HELP = (
    "σ (µm) of the Gaussian smoothing of profilometer scans before registration "
    "(default: data/profile_cnn.toml, 1.25; 0 = none). Scan noise otherwise moves "
    "the stage-1 targets' edges by ~19 µm."
)


def _smoothing_option(f):
    return click.option("--scan-smoothing-um", type=float, default=None, help=_SMOOTHING_HELP)(f)


def _synthetic(n_pairs, n_columns, seed, um_per_px, progress, scan_smoothing_um=None):
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.profile_cnn.synth import synthetic_labelled, synthetic_pairs

    pairs = synthetic_pairs(
        n_pairs,
        seed=seed,
        um_per_px=um_per_px,
        progress=progress,
        scan_smoothing_um=scan_smoothing_um,
    )
    labelled = synthetic_labelled(n_columns, seed=seed, um_per_px=um_per_px, progress=progress)
    return pairs, labelled


def _load_data(
    pairs_path,
    columns_path,
    synthetic,
    n_pairs,
    n_columns,
    seed,
    um_per_px,
    progress,
    scan_smoothing_um=None,
):
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.profile_cnn.data import load_dataset

    if synthetic:
        if pairs_path or columns_path:
            raise click.UsageError("--synthetic replaces --pairs/--columns; give one or the other")
        return _synthetic(n_pairs, n_columns, seed, um_per_px, progress, scan_smoothing_um)
    if not pairs_path and not columns_path:
        raise click.UsageError("give --pairs and/or --columns data sets, or --synthetic")
    try:
        pairs = load_dataset(pairs_path) if pairs_path else None
        labelled = load_dataset(columns_path) if columns_path else None
    except (ValueError, FileNotFoundError) as exc:
        raise click.ClickException(str(exc)) from None
    return pairs, labelled


@functools.cache
def _training_recipe() -> dict:
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.profile_cnn.data import settings

    return settings()["training"]


def _recipe(key):
    """The default of a training option: data/profile_cnn.toml [training]."""
    return _training_recipe()[key]


def _apply(options, f):
    """Decorate ``f`` with click options (the first listed is the first shown)."""
    for option in reversed(options):
        f = option(f)
    return f


def _schedule_options() -> list:
    """Seed, epochs, batch size and learning rates of the two training stages."""
    return [
        click.option("--seed", type=int, default=0, show_default=True),
        click.option("--stage1-epochs", type=int, default=100, show_default=True),
        click.option("--stage2-epochs", type=int, default=50, show_default=True),
        click.option("--batch-size", type=int, default=32, show_default=True),
        click.option("--stage1-lr", type=float, default=1e-3, show_default=True),
        click.option("--stage2-lr", type=float, default=2e-4, show_default=True),
    ]


def _recipe_options() -> list:
    """The options whose defaults are the training recipe (``data/profile_cnn.toml``)."""
    return [
        click.option(
            "--stage1-area-weight",
            type=float,
            default=_recipe("stage1_area_weight"),
            show_default=f"{_recipe('stage1_area_weight')}, data/profile_cnn.toml",
            help="Weight of the relative cross-section area (Q_m) term in the stage-1 loss.",
        ),
        click.option(
            "--grad-clip",
            type=float,
            default=_recipe("grad_clip"),
            show_default=f"{_recipe('grad_clip')}, data/profile_cnn.toml",
            help="Gradient-norm clip of every step.",
        ),
        click.option(
            "--val-fraction",
            type=float,
            default=_recipe("val_fraction"),
            show_default=f"{_recipe('val_fraction')}, data/profile_cnn.toml",
            help="Share of the stage-2 column groups held back to pick the best stage-2 "
            "epoch (0 = keep the last epoch).",
        ),
        click.option(
            "--restarts",
            type=int,
            default=_recipe("restarts"),
            show_default=f"{_recipe('restarts')}, data/profile_cnn.toml",
            help="Train N runs (seeds SEED, SEED+1, ...) and keep the best by the stage-2 "
            "validation score (needs --val-fraction).",
        ),
        click.option(
            "--restart-screen-epochs",
            type=int,
            default=_recipe("restart_screen_epochs"),
            show_default=f"{_recipe('restart_screen_epochs')}, data/profile_cnn.toml",
            help="With --restarts: train each restart to this stage-2 epoch, then finish "
            "only the --restart-finalists best (0 = finish all).",
        ),
        click.option(
            "--restart-finalists",
            type=int,
            default=_recipe("restart_finalists"),
            show_default=f"{_recipe('restart_finalists')}, data/profile_cnn.toml",
            help="Restarts finished after the screen.",
        ),
    ]


def _loss_and_network_options() -> list:
    """The loss terms beside the paper's, the network and its width, torch threads."""
    return [
        click.option(
            "--stage1-brightness-weight",
            type=float,
            default=0.0,
            show_default=True,
            help="Weight of the brightness (slope) term in the stage-1 loss; 0 = plain MSE.",
        ),
        click.option(
            "--replay-weight",
            type=float,
            default=0.0,
            show_default=True,
            help="Stage-1 profile loss mixed into stage 2 (0 = the paper's pure feature loss).",
        ),
        click.option(
            "--area-weight",
            type=float,
            default=1000.0,
            show_default=True,
            help="Stage-2 anchor keeping each column's area (Q_m) at the stage-1 model's; "
            "0 = the paper's pure feature loss (inflates Q_m; see "
            "docs/explanation/profile-cnn.md).",
        ),
        click.option(
            "--arch",
            type=click.Choice(["resnet18", "unet1d"]),
            default=_recipe("arch"),
            show_default=f"{_recipe('arch')}, data/profile_cnn.toml",
            help="Network: the paper's 1-D ResNet-18, or a small 1-D U-Net "
            "(docs/explanation/profile-cnn.md).",
        ),
        click.option(
            "--width",
            "base_channels",
            type=int,
            default=None,
            help="Channels of the first stage (default: 64 = ResNet-18's 64-512; U-Net 16).",
        ),
        click.option("--threads", type=int, default=None, help="torch threads (default 1)."),
    ]


def _data_options() -> list:
    """Where the training data come from: synthetic, or stage-1/stage-2 files."""
    return [
        click.option("--synthetic", is_flag=True, help="Train on synthetic rendered data."),
        click.option(
            "--pairs",
            "pairs_path",
            type=click.Path(dir_okay=False),
            default=None,
            help="Stage-1 pairs NPZ (columns + profiles_um).",
        ),
        click.option(
            "--columns",
            "columns_path",
            type=click.Path(dir_okay=False),
            default=None,
            help="Stage-2 NPZ (columns + linewidth_um/overspray_um CV labels).",
        ),
        click.option(
            "--n-pairs", type=int, default=125, show_default=True, help="Synthetic stage-1 pairs."
        ),
        click.option(
            "--n-columns",
            type=int,
            default=4000,
            show_default=True,
            help="Synthetic stage-2 columns.",
        ),
        click.option(
            "--um-per-px",
            type=float,
            default=0.75,
            show_default=True,
            help="Pixel size of synthetic data, µm.",
        ),
        click.option(
            "--scan-smoothing-um",
            type=float,
            default=None,
            help="With --synthetic: " + _SMOOTHING_HELP,
        ),
        click.option("--progress/--no-progress", default=True, show_default=True),
    ]


def _training_options(f):
    """Every option of ``cnn train`` and ``cnn crossval``."""
    options = _schedule_options() + _recipe_options() + _loss_and_network_options()
    return _apply(options + _data_options(), f)


def _config(kw):
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.profile_cnn.train import TrainConfig

    return TrainConfig(
        seed=kw["seed"],
        stage1_epochs=kw["stage1_epochs"],
        stage2_epochs=kw["stage2_epochs"],
        batch_size=kw["batch_size"],
        stage1_lr=kw["stage1_lr"],
        stage2_lr=kw["stage2_lr"],
        stage1_brightness_weight=kw["stage1_brightness_weight"],
        stage2_replay_weight=kw["replay_weight"],
        stage2_area_weight=kw["area_weight"],
        stage2_val_fraction=kw["val_fraction"],
        grad_clip=kw["grad_clip"],
        stage1_area_weight=kw["stage1_area_weight"],
        restarts=kw["restarts"],
        restart_screen_epochs=kw["restart_screen_epochs"],
        restart_finalists=kw["restart_finalists"],
        base_channels=kw["base_channels"],
        arch=kw["arch"],
        n_threads=kw["threads"],
    )


@click.group()
def cnn():
    """Height-profile CNN (paper §5): train, cross-validate, infer Q_m from video."""


@cnn.command()
@click.option("--out-dir", type=click.Path(file_okay=False), required=True)
@click.option("--n-pairs", type=int, default=125, show_default=True)
@click.option("--n-columns", type=int, default=4000, show_default=True)
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--um-per-px", type=float, default=0.75, show_default=True)
@_smoothing_option
@click.option("--progress/--no-progress", default=True, show_default=True)
def synth(out_dir, n_pairs, n_columns, seed, um_per_px, scan_smoothing_um, progress):
    """Render synthetic training data: OUT_DIR/pairs.npz and OUT_DIR/columns.npz."""
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.profile_cnn.data import save_dataset

    pairs, labelled = _synthetic(n_pairs, n_columns, seed, um_per_px, progress, scan_smoothing_um)
    out = Path(out_dir)
    click.echo(f"wrote {save_dataset(pairs, out / 'pairs.npz')} ({len(pairs)} pairs)")
    click.echo(f"wrote {save_dataset(labelled, out / 'columns.npz')} ({len(labelled)} columns)")


@cnn.command()
@click.argument("manifest", type=click.Path(exists=True, dir_okay=False))
@click.option("--um-per-px", type=float, required=True, help="Camera pixel size, µm.")
@click.option("--out", type=click.Path(dir_okay=False), required=True)
@click.option(
    "--half-width-px",
    type=int,
    default=0,
    show_default=True,
    help="Average 2·N+1 neighbouring frame columns per pair.",
)
@_smoothing_option
def pairs(manifest, um_per_px, out, half_width_px, scan_smoothing_um):
    """Build stage-1 pairs from real frames and profilometer scans (MANIFEST CSV).

    Columns: frame, column_px, line_row_px, scan, scan_row, scan_pixel_size_um
    (blank = from the scan file), optional height_unit. See docs/explanation/profile-cnn.md.
    """
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.profile_cnn.data import pairs_from_manifest, save_dataset

    try:
        data = pairs_from_manifest(
            manifest,
            um_per_px,
            half_width_px=half_width_px,
            scan_smoothing_um=scan_smoothing_um,
        )
    except (ValueError, FileNotFoundError) as exc:
        raise click.ClickException(str(exc)) from None
    click.echo(f"wrote {save_dataset(data, out)} ({len(data)} pairs)")


@cnn.command()
@click.argument("video", type=click.Path(exists=True))
@click.option("--um-per-px", type=float, required=True, help="Camera pixel size, µm.")
@click.option("--out", type=click.Path(dir_okay=False), required=True)
@click.option("--batch", type=int, default=50, show_default=True, help="Columns per batch.")
@click.option("--fps", type=float, default=None, help="Frame rate override.")
@click.option("--progress/--no-progress", default=True, show_default=True)
def columns(video, um_per_px, out, batch, fps, progress):
    """Stage-2 data from real VIDEO: batch columns labelled by the CV extractor."""
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.profile_cnn.data import save_dataset
    from ajtwin.profile_cnn.frames import labelled_columns_from_video
    from ajtwin.vision.extract import VisionInputError

    try:
        data = labelled_columns_from_video(
            video, um_per_px, batch=batch, fps=fps, progress=progress
        )
    except (ValueError, VisionInputError) as exc:
        raise click.ClickException(str(exc)) from None
    click.echo(f"wrote {save_dataset(data, out)} ({len(data)} labelled columns)")


@cnn.command()
@_training_options
@click.option("--out", type=click.Path(dir_okay=False), required=True, help="Model file (.pt).")
@click.option(
    "--checkpoint",
    type=click.Path(dir_okay=False),
    default=None,
    help="Checkpoint written every epoch (default: OUT.ckpt).",
)
@click.option("--resume", is_flag=True, help="Continue from the checkpoint if it exists.")
@click.option(
    "--init",
    "init_path",
    type=click.Path(exists=True, dir_okay=False),
    default=None,
    help="Start from this model (e.g. fine-tune only with --columns).",
)
def train(out, checkpoint, resume, init_path, **kw):
    """Train the CNN: stage 1 on profile pairs, stage 2 on CV-labelled columns."""
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.profile_cnn.model import ProfileModel
    from ajtwin.profile_cnn.train import train_restarts

    pairs_ds, labelled = _load_data(
        kw["pairs_path"],
        kw["columns_path"],
        kw["synthetic"],
        kw["n_pairs"],
        kw["n_columns"],
        kw["seed"],
        kw["um_per_px"],
        kw["progress"],
        kw["scan_smoothing_um"],
    )
    config = _config(kw)
    init = ProfileModel.load(init_path) if init_path else None
    checkpoint = checkpoint or str(out) + ".ckpt"
    try:
        model, trainers, best = train_restarts(
            config,
            pairs_ds,
            labelled,
            init_model=init,
            checkpoint=checkpoint,
            resume=resume,
            progress=kw["progress"],
        )
    except ValueError as exc:
        raise click.ClickException(str(exc)) from None
    model.meta["command"] = (
        click.get_current_context().command_path
        + " "
        + json.dumps({k: v for k, v in kw.items() if k != "progress"})
    )
    model.save(out)
    if len(trainers) > 1:
        for r, entry in enumerate(model.meta["restarts"]):
            mark = "kept" if r == best else ""
            screened = (
                f"screen {entry['screen_val_score_um']} µm, "
                if entry["screen_val_score_um"] is not None
                else ""
            )
            finished = (
                f"validation score {entry['val_score_um']} µm at stage-2 epoch "
                f"{entry['selected_epoch']}"
                if entry["finished"]
                else "not finished"
            )
            click.echo(f"restart {r + 1}: seed {entry['seed']}, {screened}{finished} {mark}")
    stage1 = sum(t.stage_seconds["1"] for t in trainers)
    stage2 = sum(t.stage_seconds["2"] for t in trainers)
    over = f" over {len(trainers)} restarts" if len(trainers) > 1 else ""
    click.echo(
        f"wrote {out} (stage 1 {stage1:.0f} s, stage 2 {stage2:.0f} s{over}; "
        f"checkpoint {checkpoint})"
    )


@cnn.command()
@_training_options
@click.option("--folds", "k", type=int, default=10, show_default=True)
@click.option("--only-fold", "only", type=int, multiple=True, help="Run just these folds.")
@click.option("--out", type=click.Path(dir_okay=False), required=True, help="Results JSON.")
def crossval(k, only, out, **kw):
    """K-fold cross-validation of two-stage training (paper: k = 10).

    Writes OUT after every fold; re-running with the same settings skips the
    folds already done.
    """
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.profile_cnn.evaluate import cross_validate

    pairs_ds, labelled = _load_data(
        kw["pairs_path"],
        kw["columns_path"],
        kw["synthetic"],
        kw["n_pairs"],
        kw["n_columns"],
        kw["seed"],
        kw["um_per_px"],
        kw["progress"],
        kw["scan_smoothing_um"],
    )
    if pairs_ds is None or labelled is None:
        raise click.UsageError("cross-validation needs both --pairs and --columns (or --synthetic)")
    result = cross_validate(
        pairs_ds,
        labelled,
        _config(kw),
        k=k,
        folds=list(only) or None,
        out_json=out,
        progress=kw["progress"],
    )
    s = result["summary"]
    for key in (
        "before_columns.mae_linewidth_vs_cv_um",
        "after_columns.mae_linewidth_vs_cv_um",
        "before_columns.mae_overspray_vs_cv_um",
        "after_columns.mae_overspray_vs_cv_um",
        "before_pairs.qm_rel_error",
        "after_pairs.qm_rel_error",
    ):
        if f"{key}.mean" in s:
            click.echo(f"{key}: {s[key + '.mean']:.4g} (fold variance {s[key + '.var']:.3g})")
    click.echo(f"wrote {out}")


@cnn.command()
@click.option("--model", "model_path", type=click.Path(exists=True, dir_okay=False), required=True)
@click.option("--pairs", "pairs_path", type=click.Path(exists=True, dir_okay=False), default=None)
@click.option(
    "--columns", "columns_path", type=click.Path(exists=True, dir_okay=False), default=None
)
def score(model_path, pairs_path, columns_path):
    """Score a model on held-out data sets (MAEs, Q_m error), as JSON."""
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.profile_cnn.data import load_dataset
    from ajtwin.profile_cnn.evaluate import score as score_model
    from ajtwin.profile_cnn.model import ProfileModel, set_threads

    if not pairs_path and not columns_path:
        raise click.UsageError("give --pairs and/or --columns")
    set_threads()
    model = ProfileModel.load(model_path)
    out = {}
    try:
        for name, path in (("pairs", pairs_path), ("columns", columns_path)):
            if path:
                out[name] = score_model(model, load_dataset(path))
    except ValueError as exc:
        raise click.ClickException(str(exc)) from None
    click.echo(json.dumps(out, indent=2))


@cnn.command("cv-summary")
@click.argument("parts", nargs=-1, required=True, type=click.Path(exists=True, dir_okay=False))
@click.option("--out", type=click.Path(dir_okay=False), required=True)
def cv_summary(parts, out):
    """Merge cross-validation JSONs of folds run in separate processes (--only-fold)."""
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.profile_cnn.evaluate import summarize

    merged = None
    for part in parts:
        data = json.loads(Path(part).read_text())
        if merged is None:
            merged = {"k": data["k"], "config": data["config"], "folds": []}
        elif data["config"] != merged["config"] or data["k"] != merged["k"]:
            raise click.ClickException(f"{part}: made with other settings than {parts[0]}")
        merged["folds"] += data["folds"]
    folds = sorted({f["fold"] for f in merged["folds"]})
    if len(folds) != len(merged["folds"]):
        raise click.ClickException("the same fold appears in two parts")
    merged["folds"].sort(key=lambda f: f["fold"])
    merged["summary"] = summarize(merged["folds"])
    Path(out).write_text(json.dumps(merged, indent=2))
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.profile_cnn.evaluate import report_table

    click.echo(report_table(merged["summary"]))
    click.echo(f"wrote {out} ({len(folds)} of {merged['k']} folds)")


@cnn.command()
@click.argument("video", type=click.Path(exists=True))
@click.option("--model", "model_path", type=click.Path(exists=True, dir_okay=False), required=True)
@click.option("--um-per-px", type=float, required=True, help="Camera pixel size, µm.")
@click.option("--platen-speed-mm-s", type=float, required=True, help="Platen speed ν, mm/s.")
@click.option("--out", type=click.Path(dir_okay=False), required=True, help="Q_m CSV.")
@click.option("--batch", type=int, default=50, show_default=True, help="Columns per batch.")
@click.option("--fps", type=float, default=None, help="Frame rate override.")
@join_options("material_flow_mL_s", "cnn", must_exist=True)
@click.option("--threads", type=int, default=None, help="torch threads (default 1).")
@click.option("--progress/--no-progress", default=True, show_default=True)
def infer(
    video,
    model_path,
    um_per_px,
    platen_speed_mm_s,
    out,
    batch,
    fps,
    join_record,
    join_out,
    start_offset_s,
    camera_offset_um,
    threads,
    progress,
    csv_dialect,
):
    """Material flow Q_m = ν ∫ h dr per frame of VIDEO (video, image folder or image).

    CSV columns: frame, time_s, material_flow_mL_s, then material_flow_std_mL_s
    (spread over the frame's batches), cross_section_um2, n_columns, status.
    """
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.profile_cnn.infer import infer_video
    from ajtwin.profile_cnn.model import ProfileModel, set_threads
    from ajtwin.vision.extract import VisionInputError

    set_threads(threads)
    try:
        model = ProfileModel.load(model_path)
        table = infer_video(
            video,
            model,
            um_per_px=um_per_px,
            platen_speed_mm_s=platen_speed_mm_s,
            batch=batch,
            fps=fps,
            progress=progress,
        )
    except (ValueError, VisionInputError, FileNotFoundError) as exc:
        raise click.ClickException(str(exc)) from None
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    table.to_csv(out, index=False)
    n_ok = int((table["status"] == "ok").sum())
    click.echo(f"wrote {out} ({len(table)} frames, {n_ok} with Q_m)")
    if join_record:
        _join(
            join_record,
            join_out,
            table,
            start_offset_s,
            camera_offset_um,
            platen_speed_mm_s,
            video,
            model_path,
            csv_dialect,
        )


def _join(
    record_path,
    join_out,
    table,
    start_offset_s,
    camera_offset_um,
    speed,
    video,
    model,
    csv_dialect=None,
):
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.profile_cnn.infer import join_material_flow

    record_path = Path(record_path)
    try:
        rec = read_record(record_path, dialect=csv_dialect)
        joined, summary = join_material_flow(
            rec.data,
            table,
            start_offset_s=start_offset_s,
            camera_offset_um=camera_offset_um,
            platen_speed_mm_s=speed,
        )
    except (RecordError, ValueError, FileNotFoundError) as exc:
        raise click.ClickException(str(exc)) from None
    meta = dict(rec.meta)
    meta["profile_cnn"] = {
        "source": str(video),
        "model": str(model),
        "platen_speed_mm_s": speed,
        "start_offset_s": start_offset_s,
        "camera_offset_um": camera_offset_um,
        **summary,
    }
    join_out = (
        Path(join_out) if join_out else record_path.with_name(record_path.stem + "_cnn.parquet")
    )
    path = write_record(PrintRecord(joined, meta), join_out)
    click.echo(f"wrote {path} ({json.dumps(summary)})")
    if summary["seconds_filled"] == 0:
        raise click.ClickException(
            "no video frame fell inside the record's time span: check --start-offset, "
            "--camera-offset and the frame rate"
        )
