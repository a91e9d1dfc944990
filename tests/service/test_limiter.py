"""The limiter's slots (``service.api.limiter``) in an event loop of their own: a job whose client went away or
whose deadline passed is dropped without leaving an exception for asyncio to report later."""

from __future__ import annotations

import asyncio
import gc
import time

from starlette.requests import ClientDisconnect

from service.api.limiter import DeadlineExceededError, InferenceLimiter


def failing_job() -> None:
    time.sleep(0.3)
    raise RuntimeError("the job's own failure, after nobody waits for it")


async def gone() -> bool:
    return True


def run_and_collect_reports(limiter: InferenceLimiter, disconnected=None) -> tuple[int, list[dict]]:
    """Run ``failing_job`` in a slot until it is dropped (as a route would: the error answered, then forgotten), let
    the job end, collect garbage: the status the slot raised and what the loop's exception handler was given
    (asyncio's "exception was never retrieved" reports)."""
    reports: list[dict] = []

    async def route() -> int:  # its slot and the job's futures are dropped when it returns, as a route's are
        try:
            with limiter.admit() as slot:
                await slot.run(failing_job, disconnected)
        except ClientDisconnect:
            return 499  # as the access middleware records it
        except DeadlineExceededError as exc:
            return exc.status
        return 200

    async def main() -> int:
        asyncio.get_running_loop().set_exception_handler(lambda loop, context: reports.append(context))
        status = await route()
        await asyncio.sleep(0.6)  # the job ends with its exception
        gc.collect()
        await asyncio.sleep(0.05)
        return status

    return asyncio.run(main()), reports


def test_a_job_whose_client_went_away_leaves_nothing_to_report() -> None:
    status, reports = run_and_collect_reports(InferenceLimiter(1, 0, timeout_s=30.0), gone)
    assert status == 499
    assert reports == []


def test_a_job_past_its_deadline_leaves_nothing_to_report() -> None:
    status, reports = run_and_collect_reports(InferenceLimiter(1, 0, timeout_s=0.05))
    assert status == 504
    assert reports == []
