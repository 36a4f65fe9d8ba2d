"""Many photos against one model, resumable and shardable across cluster jobs.

Planning (``planning.py``), the workers (``worker.py``) and the rows they record
(``records.py``) in ``poses.json`` / ``poses.csv`` (``app/ledger.py``).

    plan, mf = plan_batch(data)                       # the tool's data group (model_folder)
    setup = WorkerSetup(model_path=..., method=RobustConfig(), matcher={...}, out_dir=...)
    ledger = PosesLedger(out_dir, run=run_identity("batch", data, ...), total=len(plan.tasks))
    summary = run_batch(plan, setup, ledger, workers=2)
"""
from .planning import BatchPlan, PhotoTask, plan_batch, run_identity, select
from .records import export_rows, failure_row, result_row, safe_name
from .worker import BatchSummary, BatchWorker, WorkerSetup, run_batch

__all__ = [
    "BatchPlan",
    "BatchSummary",
    "BatchWorker",
    "PhotoTask",
    "WorkerSetup",
    "export_rows",
    "failure_row",
    "plan_batch",
    "result_row",
    "run_batch",
    "run_identity",
    "safe_name",
    "select",
]
