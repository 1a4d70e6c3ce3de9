"""``ajtwin cfd`` — build the output macro-model from OpenFOAM (model reference §8).

ajtwin cfd case  OUT --dRN 0 --qc 23 --qs 50           write an OpenFOAM case
ajtwin cfd run   OUT --dRN 0 --qc 23 --qs 50 --da 3.5  solve + droplets + L_w, L_o
ajtwin cfd sweep OUT --design full [--scheduler tcp://host:8786]
ajtwin cfd fit   OUT --coefficients coeffs.toml --resistance nozzle_fit.toml
ajtwin cfd report OUT [--compare FINE_SWEEP]            validation figures, mesh study
"""

from __future__ import annotations

import functools
import json
from pathlib import Path

import click
import pandas as pd

from ajtwin.config import packaged_toml, read_toml


def _spec_options(func):
    func = click.option(
        "--mesh-level",
        default=1,
        show_default=True,
        type=int,
        help="Mesh refinement (1 coarse, 2 = twice the cells per direction).",
    )(func)
    func = click.option(
        "--qs",
        "sheath",
        default=50.0,
        show_default=True,
        type=float,
        help="Sheath flow Q_s [sccm].",
    )(func)
    func = click.option(
        "--qc",
        "carrier",
        default=23.0,
        show_default=True,
        type=float,
        help="Carrier flow Q_c [sccm].",
    )(func)
    func = click.option(
        "--dRN",
        "deposition",
        default=0.0,
        show_default=True,
        type=float,
        help="Nozzle deposition ΔR_N [µm] (tip walls moved inward).",
    )(func)
    return click.option(
        "--geometry",
        type=click.Path(exists=True, dir_okay=False),
        help="Geometry TOML (default: the packaged geometry.toml).",
    )(func)


def _spec(deposition, carrier, sheath, mesh_level):
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.cfd.case import CaseSpec

    try:
        return CaseSpec(deposition, carrier, sheath, mesh_level=mesh_level)
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None


def _geometry(path):
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.cfd.geometry import load_geometry

    try:
        return load_geometry(path)
    except (ValueError, OSError) as exc:
        raise click.BadParameter(str(exc), param_hint="--geometry") from None


_droplet_range_option = click.option(
    "--droplet-range",
    nargs=2,
    type=float,
    help="Fit the linear d_a term on sweep rows with LOW ≤ d_a ≤ HIGH µm "
    "(default: [fit] droplet_range_um of sweep.toml, 3.0 4.0).",
)


def _fit_window(droplet_range) -> tuple[float, float]:
    """The d_a window of the fit: the option if given, else sweep.toml's [fit]."""
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.cfd.fit import fit_settings

    return tuple(droplet_range) if droplet_range else fit_settings()["droplet_range_um"]


def _foam_errors(func):

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        # lazy CLI loading: imported when the command runs, not for --help
        from ajtwin.cfd.foam import OpenFoamError, OpenFoamMissing

        try:
            return func(*args, **kwargs)
        except OpenFoamMissing as exc:
            raise click.ClickException(str(exc)) from None
        except OpenFoamError as exc:
            raise click.ClickException(str(exc)) from None

    return wrapper


@click.group()
def cfd():
    """CFD macro-model with OpenFOAM v1912: output coefficients and nozzle resistance."""


@cfd.command()
@click.argument("out", type=click.Path(file_okay=False))
@_spec_options
def case(out, geometry, deposition, carrier, sheath, mesh_level):
    """Write an OpenFOAM case (axisymmetric wedge of the deposition head) to OUT."""
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.cfd.case import write_case

    spec = _spec(deposition, carrier, sheath, mesh_level)
    path = write_case(spec, out, _geometry(geometry))
    click.echo(
        f"wrote {spec.name} to {path} (run: source /usr/share/openfoam/etc/bashrc; "
        f"cd {path}; blockMesh; simpleFoam)"
    )


@cfd.command()
@click.argument("out", type=click.Path(file_okay=False))
@_spec_options
@click.option(
    "--da",
    "diameters",
    multiple=True,
    type=float,
    default=(3.5,),
    show_default=True,
    help="Median droplet diameter d_a [µm]; repeat for several.",
)
@click.option("--droplets", default=3000, show_default=True, help="Droplets tracked per d_a.")
@click.option("--force", is_flag=True, help="Re-run even if OUT holds a finished result.")
@_foam_errors
def run(out, geometry, deposition, carrier, sheath, mesh_level, diameters, droplets, force):
    """Solve one case and report max gas speed, R_3^N, linewidth and overspray."""
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.cfd.run import run_case

    spec = _spec(deposition, carrier, sheath, mesh_level)
    result = run_case(spec, out, diameters, droplets, geometry=_geometry(geometry), force=force)
    flow = result["flow"]
    click.echo(
        f"case {spec.name}: {flow['cells']} cells, {flow['iterations']} iterations, "
        f"converged={flow['converged']} (U residual {flow['final_residual_u']:.1e})"
    )
    click.echo(f"  max gas speed          {flow['max_speed_m_s']:.1f} m/s")
    click.echo(f"  R_3^N (cone entry→amb) {flow['tip_resistance_pa_s_m3']:.3e} Pa s/m3")
    click.echo(
        f"  carrier/sheath inlet p {flow['carrier_inlet_pressure_pa']:.0f} / "
        f"{flow['sheath_inlet_pressure_pa']:.0f} Pa"
    )
    for row in result["droplets"]:
        click.echo(
            f"  d_a {row['droplet_diameter_um']:.2f} µm: L_w {row['linewidth_um']:.1f} µm, "
            f"L_o {row['overspray_um']:.1f} µm, landed {row['fraction_landed']:.1%}, "
            f"wall {row['fraction_wall']:.1%}"
        )
    click.echo(f"  wall time {result['wall_time_s']:.1f} s")


@cfd.command()
@click.argument("out", type=click.Path(file_okay=False))
@click.option(
    "--design",
    default="full",
    show_default=True,
    help="Sweep design in ajtwin/cfd/sweep.toml (full, coarse, smoke).",
)
@click.option(
    "--design-file",
    type=click.Path(exists=True, dir_okay=False),
    help="Use designs from this TOML instead of the packaged sweep.toml.",
)
@click.option("--mesh-level", type=int, help="Override the design's mesh level.")
@click.option("--scheduler", help="Dask scheduler address (default: a local cluster).")
@click.option("--workers", default=2, show_default=True, help="Local Dask workers (1 thread each).")
@click.option(
    "--no-retry-failed", is_flag=True, help="Keep earlier failures instead of re-running."
)
@_foam_errors
def sweep(out, design, design_file, mesh_level, scheduler, workers, no_retry_failed):
    """Run or resume a sweep in OUT (finished cases are skipped, failures recorded)."""
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.cfd.sweep import load_design, run_sweep

    try:
        plan = load_design(design, design_file, mesh_level)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--design") from None
    table = run_sweep(
        plan, out, scheduler=scheduler, workers=workers, retry_failed=not no_retry_failed
    )
    meta = json.loads((Path(out) / "sweep.json").read_text())
    n_failed = len(meta["failed"])
    click.echo(
        f"sweep {plan.name}: {len(plan.cases)} cases, {n_failed} failed, "
        f"{len(table)} rows; wall time {meta['wall_time_s']:.0f} s; "
        f"summary {Path(out) / 'summary.csv'}"
    )
    for name in meta["failed"]:
        click.echo(f"  failed: {name}", err=True)


@cfd.command()
@click.argument("sweep_dir", type=click.Path(exists=True, file_okay=False))
@click.option(
    "--coefficients",
    "coefficients_out",
    type=click.Path(dir_okay=False),
    default="output_coefficients_cfd.toml",
    show_default=True,
    help="Where to write the output-model coefficient file.",
)
@click.option(
    "--resistance",
    "resistance_out",
    type=click.Path(dir_okay=False),
    default="nozzle_resistance_fit.toml",
    show_default=True,
    help="Where to write the R_3^N(ΔR_N) fit.",
)
@click.option(
    "--reference",
    type=click.Path(exists=True, dir_okay=False),
    help="Coefficient file supplying alpha^phi (default: the packaged one).",
)
@click.option(
    "--table-record",
    help="Where the sweep table is kept for the record (e.g. level2_u4/summary.csv under "
    "ajtwin/cfd/results); written into the coefficient file. Default: SWEEP_DIR/summary.csv.",
)
@_droplet_range_option
def fit(sweep_dir, coefficients_out, resistance_out, reference, table_record, droplet_range):
    """Fit output-model coefficients and R_3^N(ΔR_N) to a finished sweep.

    To adopt a fit as the twin's output model, write it over
    ajtwin/data/output_coefficients.toml (with --reference pointing at the
    provisional file that supplies alpha^phi).
    """

    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.cfd import fit as fitting
    from ajtwin.cfd.report import sweep_metadata

    sweep_dir = Path(sweep_dir)
    summary = sweep_dir / "summary.csv"
    if not summary.exists():
        raise click.ClickException(f"{summary} not found: run `ajtwin cfd sweep {sweep_dir}` first")
    table = pd.read_csv(summary)
    ref = read_toml(reference, what="reference coefficient") if reference else _packaged_reference()
    meta = sweep_metadata(sweep_dir, table)
    meta["summary_table"] = table_record or str(summary)
    limit = _geometry(None).max_trusted_speed
    try:
        result = fitting.fit_output_model(table, ref, limit, _fit_window(droplet_range))
        resistance = fitting.fit_tip_resistance(table, tuple(meta["nominal"]), max_speed_m_s=limit)
    except ValueError as exc:
        raise click.ClickException(f"{summary}: {exc}") from None
    fitting.write_toml(fitting.coefficient_document(result, meta), coefficients_out)
    fitting.write_toml(fitting.resistance_document(resistance, meta), resistance_out)
    for output in ("linewidth", "overspray"):
        c = result[output]
        click.echo(
            f"{output}: "
            + ", ".join(f"{k}={c[k]:.4g}" for k in fitting.COEFFICIENT_KEYS)
            + f"  (rms {c['rms_um']:.2f} µm, R² {c['r2']:.3f}, {c['rows']} rows)"
        )
    click.echo(
        "signs: " + ", ".join(f"{k}={v}" for k, v in fitting.sensitivity_signs(result).items())
    )
    click.echo(
        f"R_3^N: CFD a0 {resistance['cfd_a0_pa_s_m3']:.3e} vs paper "
        f"{resistance['paper_a0_pa_s_m3']:.3e}; a1 {resistance['cfd_a1_pa_s_m3_per_um']:.3e}"
        f" vs {resistance['paper_a1_pa_s_m3_per_um']:.3e} per µm"
    )
    click.echo(f"wrote {coefficients_out} and {resistance_out}")


@cfd.command()
@click.argument("sweep_dir", type=click.Path(exists=True, file_okay=False))
@click.option(
    "--compare",
    "fine_dir",
    type=click.Path(exists=True, file_okay=False),
    help="A sweep of (some of) the same cases on a finer mesh: coefficient change.",
)
@click.option("--json-out", type=click.Path(dir_okay=False), help="Also write the figures here.")
@_droplet_range_option
@click.option(
    "--plot",
    "plot_out",
    type=click.Path(dir_okay=False),
    help="PNG of L_w, L_o and landing radius vs d_a at the nominal case (both sweeps).",
)
def report(sweep_dir, fine_dir, json_out, droplet_range, plot_out):
    """Validation figures against the paper (and a mesh-independence comparison)."""

    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.cfd import fit as fitting
    from ajtwin.cfd import report as reporting

    sweep_dir = Path(sweep_dir)
    table = pd.read_csv(sweep_dir / "summary.csv")
    meta = reporting.sweep_metadata(sweep_dir, table)
    limit = _geometry(None).max_trusted_speed
    ref = _packaged_reference()
    window = _fit_window(droplet_range)
    fitted = fitting.fit_output_model(table, ref, limit, window)
    resistance = fitting.fit_tip_resistance(table, tuple(meta["nominal"]), max_speed_m_s=limit)
    figures = {
        "sweep": {
            k: meta.get(k)
            for k in ("design", "mesh_level", "cells", "cases", "wall_time_s", "runs", "failed")
        },
        "validation": reporting.validation(table, fitted, resistance),
        "fit": fitted,
        "resistance": resistance,
    }
    v = figures["validation"]
    click.echo(
        f"sweep {meta.get('design')} (mesh level {meta['mesh_level']}, "
        f"{meta['cells']} cells): wall time {meta['wall_time_s']:.0f} s over "
        f"{len(meta.get('runs', []))} run(s); failed: {meta.get('failed') or 'none'}"
    )
    click.echo(
        f"max gas speed 25/50 sccm: {v['max_speed_m_s_25_50']:.1f} m/s "
        f"(paper {v['paper_max_speed_m_s_25_50']})"
    )
    click.echo(
        f"R_3^N(0): {v['tip_resistance_a0_pa_s_m3']:.3e} Pa s/m3 (paper "
        f"{v['paper_a0_pa_s_m3']:.3e}); slope {v['tip_resistance_a1_pa_s_m3_per_um']:.3e}"
        f" per µm (paper {v['paper_a1_pa_s_m3_per_um']:.3e})"
    )
    click.echo(
        f"L_w 23/50 sccm, d_a 3.5 µm: CFD {v['linewidth_um_23_50_da3.5']:.1f} µm, fitted "
        f"model {v['model_linewidth_um_23_50_da3.5']:.1f} µm "
        f"(paper {v['paper_linewidth_um']:g}); L_o {v['overspray_um_23_50_da3.5']:.1f} µm"
    )
    click.echo("signs: " + ", ".join(f"{k}={val}" for k, val in v["signs"].items()))
    if fine_dir:
        fine = pd.read_csv(Path(fine_dir) / "summary.csv")
        comparison = reporting.mesh_comparison(table, fine, ref, limit, window)
        figures["mesh_comparison"] = comparison
        click.echo(
            f"mesh study on {comparison['rows']} matched rows "
            f"({comparison['cells_coarse']} vs {comparison['cells_fine']} cells):"
        )
        for output in ("linewidth", "overspray"):
            c = comparison[output]
            click.echo(
                f"  {output}: mean |case change| {c['mean_abs_case_change_um']:.2f} µm "
                f"(mean {c['mean_case_change_um']:+.2f})"
            )
            for key in fitting.COEFFICIENT_KEYS:
                if key in c:
                    click.echo(f"    {key:20s} {c[key]['coarse']:12.5g} -> {c[key]['fine']:12.5g}")
        click.echo(
            f"  max speed max rel change {comparison['max_speed_m_s_max_rel_change']:.2%}, "
            f"R_3^N {comparison['tip_resistance_pa_s_m3_max_rel_change']:.2%}"
        )
    if json_out:
        Path(json_out).write_text(json.dumps(figures, indent=2, default=float))
    if plot_out:
        tables = {f"mesh level {meta['mesh_level']} ({meta['cells']} cells)": table}
        if fine_dir:
            fine_meta = reporting.sweep_metadata(Path(fine_dir), fine)
            tables[f"mesh level {fine_meta['mesh_level']} ({fine_meta['cells']} cells)"] = fine
        reporting.plot_nominal_line(tables, plot_out, tuple(meta["nominal"]))
        click.echo(f"wrote {plot_out}")


def _packaged_reference() -> dict:
    """The provisional coefficients (for alpha^phi), wherever they are kept now."""
    for name in ("output_coefficients_provisional.toml", "output_coefficients.toml"):
        try:
            return packaged_toml(f"data/{name}")
        except FileNotFoundError:
            continue
    raise click.ClickException("no packaged output-coefficient file found (need alpha^phi)")
