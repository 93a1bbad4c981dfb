"""Click commands for a finished run: report, export camtrapdp, check."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import click
import yaml

from trapflow.cli.exit import bad_input, failed
from trapflow.cli.outputs import In, Out, check_outputs, force_option, replacing_folder
from trapflow.errors import yaml_problem

if TYPE_CHECKING:
    from trapflow.config.schema import Config

# Metadata file keys (YAML) -> Deployment fields; flags of the same name override them.
META_KEYS = {"latitude": "latitude", "longitude": "longitude", "deployment_id": "deployment_id",
             "location_name": "location_name", "location_id": "location_id",
             "depth": "depth_m", "height": "height_m", "tilt": "tilt_deg",
             "heading": "heading_deg", "setup_by": "setup_by", "habitat": "habitat",
             "camera_model": "camera_model", "comments": "comments", "project": "project",
             "contributor": "contributor", "taxa": "taxa"}


@click.command()
@click.argument("run_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="HTML file to write (default: RUN_DIR/report.html).")
@click.option("--config", "config_path", type=click.Path(dir_okay=False), default=None,
              help="The run's YAML config (observe and events file names; default: built-in "
                   "defaults).")
@force_option()
def report(run_dir: Path, output: Path | None, config_path: str | None, force: bool) -> None:
    """Write one self-contained HTML page of a run: detections per class per hour, visits and
    MaxN per label per hour, length-frequency per label, VO path, pool rates over time, drops
    and losses, restarts, events."""
    from trapflow.config.schema import load
    from trapflow.errors import ConfigError
    from trapflow.export.report import ReportError, write_report
    from trapflow.export.run_files import RunInUse, finished_run

    try:
        cfg = load(config_path)
        finished_run(run_dir, "report")
        check_outputs("report", [Out(output or run_dir / "report.html", "-o")],
                      _run_inputs(run_dir, cfg, config_path), force)
        path = write_report(run_dir, output, cfg.events.folder, cfg.observe.counts_file,
                            cfg.observe.tracks_file)
    except (ConfigError, ReportError, RunInUse) as exc:
        raise bad_input(exc) from None
    click.echo(f"written: {path}")
    _say_damage(run_dir, cfg.normalizer.results_file, cfg.observe.tracks_file, "report")


def _run_inputs(run_dir: Path, cfg: Config, config_path: str | None) -> list[In]:
    """The files of a finished run that exports read: never an output."""
    names = (cfg.normalizer.results_file, cfg.observe.tracks_file, cfg.observe.counts_file,
             "ledger.json", cfg.events.folder)
    return [In(run_dir, "RUN_DIR"), *(In(run_dir / n, "RUN_DIR's") for n in names),
            *([In(Path(config_path), "--config")] if config_path else [])]


def _say_damage(run_dir: Path, results_file: str, tracks_file: str, what: str) -> None:
    """After writing what is whole: one line per cut the run's files suffered, and exit 1
    when there was one (docs/exports.md, "A damaged run")."""
    from trapflow.export.run_files import damage

    cuts = damage(run_dir, results_file, tracks_file)
    for line in cuts:
        click.echo(f"trapflow: warning: {line}", err=True)
    if cuts:
        raise failed(f"{what}: {run_dir} is damaged ({len(cuts)} cut"
                     f"{'s' if len(cuts) > 1 else ''}); what is whole was written")


@click.group("export")
def export() -> None:
    """Export a finished run to the formats camera-trap science uses."""


def _metadata(meta: Path | None) -> dict[str, Any]:
    if meta is None:
        return {}
    try:
        data = yaml.safe_load(meta.read_text(encoding="utf-8")) or {}
    except OSError as exc:
        raise bad_input(f"--meta {meta}: cannot read it: {exc.strerror}") from None
    except yaml.YAMLError as exc:
        raise bad_input(f"--meta {meta}: not valid YAML: {yaml_problem(exc)}") from None
    if not isinstance(data, dict):
        raise bad_input(f"--meta {meta}: expected a YAML mapping of deployment keys, got "
                        f"{type(data).__name__}")
    unknown = sorted(set(data) - set(META_KEYS))
    if unknown:
        raise bad_input(f"--meta {meta}: unknown keys {', '.join(map(str, unknown))}; known: "
                        f"{', '.join(META_KEYS)}")
    return {META_KEYS[k]: v for k, v in data.items()}


@export.command("camtrapdp")
@click.argument("run_dir", type=click.Path(file_okay=False, path_type=Path))
@click.argument("out", type=click.Path(file_okay=False, path_type=Path))
@click.option("--meta", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="YAML file of deployment metadata (latitude, longitude, depth, "
                   "location_name, setup_by, habitat, taxa: {label: scientific name}, ...).")
@click.option("--latitude", type=float, default=None, help="Decimal degrees, WGS84.")
@click.option("--longitude", type=float, default=None, help="Decimal degrees, WGS84.")
@click.option("--depth", type=float, default=None, help="Camera depth below the surface, m.")
@click.option("--location-name", default=None)
@click.option("--deployment-id", default=None, help="Default: the run directory's name.")
@click.option("--setup-by", default=None, help="Who deployed the trap.")
@click.option("--habitat", default=None)
@click.option("--taxon", "taxa", multiple=True, metavar="LABEL=NAME",
              help="Scientific name of a detector label, repeatable (crab='Cancer pagurus').")
@click.option("--min-confidence", type=click.FloatRange(0, 1), default=None,
              help="Least confidence of an observation (a track's best box); an image with no "
                   "box at or above it is a blank (default: export.min_confidence).")
@click.option("--config", "config_path", type=click.Path(dir_okay=False), default=None,
              help="The run's YAML config (export, observe and events file names; default: "
                   "built-in defaults).")
@force_option("Replace an OUT folder that is not empty (once the new package is whole).")
def camtrapdp(run_dir: Path, out: Path, meta: Path | None, latitude: float | None,
              longitude: float | None, depth: float | None, location_name: str | None,
              deployment_id: str | None, setup_by: str | None, habitat: str | None,
              taxa: tuple[str, ...], min_confidence: float | None,
              config_path: str | None, force: bool) -> None:
    """Write RUN_DIR's tracks and events as a Camtrap DP package in OUT (datapackage.json,
    deployments.csv, media.csv, observations.csv, media/)."""
    from trapflow.config.schema import load
    from trapflow.errors import ConfigError
    from trapflow.export.camtrapdp import Deployment, ExportError, write_package
    from trapflow.export.run_files import RunInUse, finished_run

    try:
        cfg = load(config_path)
        finished_run(run_dir, "export")
    except (ConfigError, RunInUse) as exc:
        raise bad_input(exc) from None
    check_outputs("export camtrapdp", [Out(out, "OUT", folder=True)],
                  [*_run_inputs(run_dir, cfg, config_path),
                   *([In(meta, "--meta")] if meta else [])], force)

    fields = _metadata(meta)
    flags = {"latitude": latitude, "longitude": longitude, "depth_m": depth,
             "location_name": location_name, "deployment_id": deployment_id,
             "setup_by": setup_by, "habitat": habitat}
    fields.update({k: v for k, v in flags.items() if v is not None})
    names = dict(fields.get("taxa") or {})
    for t in taxa:
        label, sep, name = t.partition("=")
        if not sep or not label or not name:
            raise bad_input(f"--taxon: expected LABEL=NAME (crab='Cancer pagurus'), got {t!r}")
        names[label] = name
    fields["taxa"] = names
    missing = [k for k in ("latitude", "longitude") if fields.get(k) is None]
    if missing:
        raise bad_input(f"export camtrapdp: Camtrap DP requires the deployment's "
                        f"{' and '.join(missing)}; pass --{missing[0]} or put it in --meta")
    try:
        with replacing_folder(out) as into:
            rows = write_package(
                run_dir, into, Deployment(**fields), cfg.events.folder,
                min_confidence=cfg.export.min_confidence if min_confidence is None
                else min_confidence, tracks_file=cfg.observe.tracks_file)
    except ExportError as exc:
        raise bad_input(exc) from None
    except TypeError as exc:  # a metadata value of the wrong kind
        raise bad_input(f"--meta {meta}: {exc}") from None
    click.echo(f"written: {out} ({len(rows.media)} media, {len(rows.observations)} "
               "observations)")
    _say_damage(run_dir, cfg.normalizer.results_file, cfg.observe.tracks_file, "export")


@click.command()
@click.argument("run_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option("--surface", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="A file `trapflow surface` wrote: each record must match a line of the run.")
@click.option("--config", "config_path", type=click.Path(dir_okay=False), default=None,
              help="The run's YAML config (results, observe file names; default: built-in "
                   "defaults).")
@click.option("--against", type=click.Path(exists=True, path_type=Path), default=None,
              help="A re-analysis of the run's pairs (a `trapflow replay` run directory, a "
                   "`trapflow process` output folder, or its results.jsonl): its pairs must "
                   "carry the live capture times, its labels the live ones where the model "
                   "is the same.")
def check(run_dir: Path, surface: Path | None, config_path: str | None,
          against: Path | None) -> None:
    """Say whether a finished run's files agree: ledger.json against results.jsonl, the
    track ids of results.jsonl against tracks.jsonl, counts.jsonl against the tracks, a
    surface file against them all, and a re-analysis of its pairs against its results.
    One line per disagreement; exit 1 when there is one."""
    from trapflow.config.schema import load
    from trapflow.errors import ConfigError
    from trapflow.export.check import check_run
    from trapflow.export.run_files import RunInUse, finished_run

    try:
        cfg = load(config_path)
        finished_run(run_dir, "check")
    except (ConfigError, RunInUse) as exc:
        raise bad_input(exc) from None
    problems = check_run(run_dir, results_file=cfg.normalizer.results_file,
                         tracks_file=cfg.observe.tracks_file,
                         counts_file=cfg.observe.counts_file, surface=surface)
    if against is not None:
        from trapflow.export.against import check_against, results_path

        more, summary = check_against(run_dir / cfg.normalizer.results_file,
                                      results_path(against))
        problems += more
        for line in summary:
            click.echo(f"against: {line}", err=True)
    for line in problems:
        click.echo(line)
    if problems:
        raise failed(f"check: {len(problems)} disagreements in {run_dir}")
    click.echo(f"{run_dir}: its files agree" + (f", and {against} tells its story"
                                                  if against is not None else ""))


COMMANDS = (report, export, check)
