"""``facecap serve``: the deployments a facecap host offers, served from this process.

* ``reconstruct-dataset/reconstruct-dataset`` — on demand (UI "Run", or
  ``prefect deployment run``), parameters ``root``, ``out``, ``config``, ``until``; served
  from this process, its captures run one after another inside it;
* ``reconstruct-capture/reconstruct-capture`` — on demand, one video;
* ``evaluate-dataset/nightly-evaluation`` — on a cron schedule (default 02:00) in a
  configurable time zone, scoring ``out`` against the scans under ``root``; a night whose
  evaluation is still running skips the next.

Workers on other machines use ``deploy/prefect.yaml`` and a process work pool instead; there a
dataset run spreads its captures over the pool's workers.
"""

from __future__ import annotations

from prefect import serve as prefect_serve
from prefect.client.schemas.objects import ConcurrencyLimitConfig, ConcurrencyLimitStrategy
from prefect.schedules import Cron

from facecap.flows.capture import reconstruct_capture
from facecap.flows.dataset import reconstruct_dataset
from facecap.flows.evaluate import evaluate_dataset

NIGHTLY_CRON = "0 2 * * *"


def deployments(root: str, out: str, cron: str = NIGHTLY_CRON, timezone: str = "UTC"):
    """The three deployments (not yet applied to a server)."""

    return [
        reconstruct_dataset.to_deployment(
            name="reconstruct-dataset", parameters={"root": root, "out": out},
            description="Reconstruct every capture of a dataset folder.",
            tags=["facecap"]),
        reconstruct_capture.to_deployment(
            name="reconstruct-capture", description="Reconstruct one capture.",
            tags=["facecap"]),
        evaluate_dataset.to_deployment(
            name="nightly-evaluation", parameters={"root": root, "out": out},
            schedules=[Cron(cron, timezone=timezone)],
            # A night whose evaluation still runs when the next is due skips the next.
            concurrency_limit=ConcurrencyLimitConfig(
                limit=1, collision_strategy=ConcurrencyLimitStrategy.CANCEL_NEW),
            description="Score the dataset's reconstructions against its scans; flag "
                        "regressions.", tags=["facecap", "nightly"]),
    ]


def serve(root: str, out: str, cron: str = NIGHTLY_CRON, timezone: str = "UTC",
          limit: int = 1) -> None:
    """Serve the deployments until interrupted (needs ``PREFECT_API_URL`` or starts the
    embedded server)."""

    prefect_serve(*deployments(root, out, cron, timezone), limit=limit)
