"""Click commands for exports of a finished run: report."""

from __future__ import annotations

from pathlib import Path

import click

from trapflow.cli_exit import bad_input


@click.command()
@click.argument("run_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="HTML file to write (default: RUN_DIR/report.html).")
def report(run_dir: Path, output: Path | None) -> None:
    """Write one self-contained HTML page of a run: detections per class per hour, VO path,
    pool rates over time, drops and losses, restarts, events."""
    from trapflow.export.report import ReportError, write_report

    try:
        path = write_report(run_dir, output)
    except ReportError as exc:
        raise bad_input(exc) from None
    click.echo(f"written: {path}")


COMMANDS = (report,)
