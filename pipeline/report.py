"""`nostra report`: the paper's tables (Markdown + CSV) and figures (PNG) from MLflow, with an index.md."""

from __future__ import annotations

from pipeline._hydra import run


def _app(cfg) -> None:
    from nostra.workflows.report import write_report

    index = write_report(cfg.report.out_dir, cfg.report.experiment)
    print(index.read_text())
    print(f"report written to {index}")


def main(argv: list[str]) -> int:
    return run("report", argv, _app)
