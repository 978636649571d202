"""`nostra compare`: the Table 4 (fine-tuning) and Table 5 (co-training) analogues from MLflow,
target only vs obj/skill vs +all per policy with deltas, as Markdown and CSV."""

from __future__ import annotations

from pipeline._hydra import run


def _app(cfg) -> None:
    from nostra.workflows.report import write_report

    index = write_report(cfg.report.compare_dir, cfg.report.experiment, only=["table4_finetune", "table5_cotrain"])
    print(index.read_text())
    print(f"comparison written to {index.parent}")


def main(argv: list[str]) -> int:
    return run("compare", argv, _app)
