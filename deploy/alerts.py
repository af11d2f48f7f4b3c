"""``facecap alerts``: notifications that reach someone when the nightly evaluation finds an
accuracy regression, or when a run of one of facecap's flows fails or crashes.

On the Prefect server in ``PREFECT_API_URL`` it creates, or updates when they exist:

* the notification block ``custom-webhook/facecap-alerts``, which POSTs ``{"text": ...}`` to
  the operator's webhook (Slack, Mattermost, Rocket.Chat, Google Chat or any HTTP endpoint);
  or it uses a notification block the operator made in the UI (``--block TYPE/NAME``);
* the automation "facecap: accuracy regressed", on the event ``facecap.evaluation.regressed``
  that flows/evaluate.py emits;
* the automation "facecap: run failed", on ``prefect.flow-run.Failed``, ``.Crashed`` and
  ``.TimedOut`` of facecap's flows (by flow name: deployed, served and command-line runs alike).

The server renders the subjects and bodies (Jinja, with ``event``, ``flow``, ``flow_run`` in
scope) when it sends them. Running this again updates everything in place: one block, one
automation of each name, and an automation the operator paused stays paused.
"""

from __future__ import annotations

from urllib.parse import urlsplit
from uuid import UUID

import httpx
from prefect.automations import Automation, EventTrigger, SendNotification
from prefect.blocks.notifications import CustomWebhookNotificationBlock
from prefect.client.orchestration import get_client
from prefect.exceptions import ObjectNotFound
from prefect.settings import PREFECT_API_URL

from facecap.flows.capture import reconstruct_capture
from facecap.flows.dataset import reconstruct_dataset
from facecap.flows.evaluate import evaluate_dataset
from facecap_core.errors import InputError
from facecap_core.settings import settings

WEBHOOK_ENV = "FACECAP_ALERT_WEBHOOK"
BLOCK_NAME = "facecap-alerts"
REGRESSED_EVENT = "facecap.evaluation.regressed"
REGRESSED = "facecap: accuracy regressed"
RUN_FAILED = "facecap: run failed"
FAILED_STATES = ("Failed", "Crashed", "TimedOut")  # TimedOut is a Failed-type state of its own

# flows/evaluate.py names the dataset in the resource id (facecap.dataset.<folder name>) and
# lists the regressions in the payload: {capture, measure, previous_mm, now_mm} each (now_mm
# None: the capture has no mesh any more).
REGRESSED_SUBJECT = (
    "facecap: accuracy regressed on "
    "{{ event.resource.id | replace('facecap.dataset.', '', 1) }}")
REGRESSED_BODY = """\
The evaluation of dataset {{ event.resource.id | replace('facecap.dataset.', '', 1) }} \
found {{ event.payload.regressions | length }} regression(s) against the previous evaluation:
{% for r in event.payload.regressions %}
- {{ r.capture }}: {{ r.measure }} {% if r.now_mm is none %}(accuracy median was \
{{ r.previous_mm }} mm){% else %}{{ r.previous_mm }} mm -> {{ r.now_mm }} mm{% endif %}
{%- endfor %}
{% if flow_run %}
Run: {{ flow_run.name }} {{ flow_run | ui_url or '' }}
{%- endif %}"""

# The state's name and message come with the event itself (the server copies them into the
# flow run's resource), so they are those of this transition even if the run moved on.
RUN_FAILED_SUBJECT = (
    "facecap: {{ flow.name }} run {{ event.resource.name }} "
    "{{ event.resource['prefect.state-name'] | lower }}")
RUN_FAILED_BODY = """\
Flow run {{ event.resource.name }} of {{ flow.name }} \
{%- if deployment %} (deployment {{ deployment.name }}){% endif %} \
ended {{ event.resource['prefect.state-name'] }}:
{{ event.resource['prefect.state-message'] or '(no message)' }}
{% if flow_run %}{{ flow_run | ui_url or '' }}{% endif %}"""


def webhook_from_environment() -> str | None:
    """The operator's webhook URL from ``$FACECAP_ALERT_WEBHOOK`` (the only place it is read)."""

    return settings().alert_webhook


def facecap_flow_names() -> list[str]:
    """The names of the flows whose failures are reported, read from the flows themselves."""

    return sorted(f.name for f in (reconstruct_capture, reconstruct_dataset, evaluate_dataset))


def check_webhook_url(url: str) -> str:
    parts = urlsplit(url)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise InputError(f"the alert webhook {url!r} is not an http(s) URL")
    return url


def webhook_block(url: str):
    """A webhook block that POSTs ``{"text": "<subject>\\n\\n<body>"}``, the shape Slack,
    Mattermost, Rocket.Chat and Google Chat take. The URL is kept among the block's secret
    values (a Slack URL is a credential), so the UI shows ``{{webhook_url}}`` in its place."""

    return CustomWebhookNotificationBlock(
        name=BLOCK_NAME, url="{{webhook_url}}", method="POST",
        json_data={"text": "{{subject}}\n\n{{body}}"}, secrets={"webhook_url": url})


def existing_block_id(client, slug_and_name: str) -> UUID:
    """The id of the notification block ``TYPE/NAME`` made in the UI (e.g.
    ``ms-teams-webhook/ops``)."""

    slug, _, name = slug_and_name.partition("/")
    if not slug or not name:
        raise InputError(f"--block {slug_and_name!r}: give the block as TYPE/NAME, e.g. "
                         "slack-webhook/ops (the block's page in the UI shows both)")
    try:
        document = client.read_block_document_by_name(name=name, block_type_slug=slug)
    except ObjectNotFound:
        raise InputError(f"no block {slug_and_name} on the Prefect server: create it under "
                         "Blocks in the UI first") from None
    if "notify" not in (document.block_schema.capabilities if document.block_schema else []):
        raise InputError(f"block {slug_and_name} cannot send notifications")
    return document.id


def regressed_automation(block_id: UUID) -> Automation:
    return Automation(
        name=REGRESSED,
        description="The nightly evaluation found a capture whose accuracy or completion "
                    "median got worse than in the previous evaluation (facecap deploy/alerts.py).",
        trigger=EventTrigger(expect={REGRESSED_EVENT}, match={"prefect.resource.id":
                                                              "facecap.dataset.*"},
                             for_each={"prefect.resource.id"}, posture="Reactive", threshold=1),
        actions=[SendNotification(block_document_id=block_id, subject=REGRESSED_SUBJECT,
                                  body=REGRESSED_BODY)])


def run_failed_automation(block_id: UUID, flow_names: list[str]) -> Automation:
    return Automation(
        name=RUN_FAILED,
        description="A run of facecap's flows ended Failed, Crashed or TimedOut (facecap "
                    "deploy/alerts.py).",
        trigger=EventTrigger(
            expect={f"prefect.flow-run.{state}" for state in FAILED_STATES},
            match={"prefect.resource.id": "prefect.flow-run.*"},
            match_related={"prefect.resource.role": "flow", "prefect.resource.name": flow_names},
            for_each={"prefect.resource.id"}, posture="Reactive", threshold=1),
        actions=[SendNotification(block_document_id=block_id, subject=RUN_FAILED_SUBJECT,
                                  body=RUN_FAILED_BODY)])


def apply_automation(client, automation: Automation) -> str:
    """Create ``automation``, or update the one of its name (deleting any duplicates of it);
    an automation the operator paused stays paused. Says which it did."""
    found = client.read_automations_by_name(automation.name)  # newest first
    if not found:
        automation.create()
        return "created"
    current, *duplicates = found
    automation.id = current.id
    automation.enabled = current.enabled
    automation.update()
    for duplicate in duplicates:
        client.delete_automation(duplicate.id)
    return "updated" + (f", {len(duplicates)} duplicate(s) removed" if duplicates else "")


def api_url() -> str:
    """The server the alerts go to: an embedded, temporary server would forget them."""

    url = PREFECT_API_URL.value()
    if not url:
        raise InputError("PREFECT_API_URL is not set: point it at the Prefect server's API "
                         "(e.g. http://localhost:4200/api) that runs facecap's flows")
    return url


def set_up_alerts(webhook: str | None = None, block: str | None = None) -> list[str]:
    """Create or update the block (``webhook``, else ``$FACECAP_ALERT_WEBHOOK``) or use the
    existing ``block``, then both automations; returns one line per thing done."""

    if block is None:
        webhook = webhook or webhook_from_environment()
        if not webhook:
            raise InputError(f"no alert webhook: pass --webhook URL, set {WEBHOOK_ENV}, or "
                             "pass --block TYPE/NAME")
        check_webhook_url(webhook)
    url = api_url()
    flow_names = facecap_flow_names()
    try:
        with get_client(sync_client=True) as client:
            if block is None:
                block_id = webhook_block(webhook).save(BLOCK_NAME, overwrite=True)
                done = [f"block custom-webhook/{BLOCK_NAME}: saved"]
            else:
                block_id = existing_block_id(client, block)
                done = [f"block {block}: used"]
            for automation in (regressed_automation(block_id),
                               run_failed_automation(block_id, flow_names)):
                done.append(f"automation {automation.name!r}: "
                            f"{apply_automation(client, automation)}")
    except httpx.HTTPStatusError as exc:
        if exc.response.status_code not in (401, 403):
            raise  # anything else is a bug here, not the operator's input
        raise InputError(f"the Prefect server at {url} refused the request (HTTP "
                         f"{exc.response.status_code}): set PREFECT_API_AUTH_STRING to its "
                         "user:password") from None
    except httpx.TransportError as exc:  # refused, unresolvable, timed out
        raise InputError(f"the Prefect server at {url} does not answer "
                         f"({type(exc).__name__}): is it running, and is PREFECT_API_URL "
                         "right?") from None
    return done
