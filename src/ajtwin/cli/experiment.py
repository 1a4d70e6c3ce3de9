"""``ajtwin experiment``: the paper's three experiments on virtual-printer prints."""

from __future__ import annotations

import json
from pathlib import Path

import click
from tqdm import tqdm

from ajtwin.cli.options import parse_seeds, transition_option, transition_overrides


@click.command("experiment")
@click.argument("name", type=click.Choice(["exp1", "exp2", "exp3"]))
@click.option("--seed", "seed", type=int, default=None, help="One seed (default 1).")
@click.option("--seeds", "seeds_text", default=None, help="Several seeds: 1-5 or 1,2,7.")
@click.option("--out", "out_dir", type=click.Path(file_okay=False), required=True)
@click.option(
    "--noise",
    "noise_tuning",
    type=click.Choice(["calibrated", "paper"]),
    default="calibrated",
    show_default=True,
)
@click.option(
    "--truth",
    type=click.Choice(["model", "alt"]),
    default="model",
    show_default=True,
    help="exp3 only: the virtual printer's truth generator; 'alt' is the second, "
    "structurally different one (ajtwin.simulation.truth_alt), for evaluation only.",
)
@transition_option
def experiment(name, seed, seeds_text, out_dir, noise_tuning, truth, transition):
    """Reproduce one of the paper's experiments on virtual prints: figures + metrics.json."""
    # lazy CLI loading: the experiments load JAX and matplotlib when they run
    from ajtwin.studies.experiment_figures import experiment_figures
    from ajtwin.studies.experiments import run_experiment

    if seed is not None and seeds_text is not None:
        raise click.UsageError("give --seed or --seeds, not both")
    seeds = parse_seeds(seeds_text) if seeds_text else [1 if seed is None else seed]
    with tqdm(total=len(seeds), unit="print", desc=name, disable=None) as bar:
        result = run_experiment(
            name,
            seeds,
            out_dir,
            {"noise_tuning": noise_tuning, **transition_overrides(transition)},
            progress=lambda _: bar.update(1),
            truth=truth,
            figures=experiment_figures,
        )
    click.echo(json.dumps(result["summary"], indent=1, default=float))
    click.echo(f"wrote figures and {Path(out_dir) / 'metrics.json'}")
