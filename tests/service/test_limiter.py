"""The limiter's slots (``service.api.limiter``) in an event loop of their own: a job whose client went away or
whose deadline passed is dropped without leaving an exception for asyncio to report later."""

from __future__ import annotations

import asyncio
import gc
import threading
import time
import weakref

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


class Upload:
    """Stands for what a queued job holds: a request's spooled upload files."""


def test_a_queued_job_dropped_before_it_starts_lets_go_of_what_it_holds() -> None:
    """While the only worker is busy, a queued job whose client went away (or whose deadline passed) is dropped: what
    its callable holds is freed then, not when the worker takes the dropped job off the executor's queue (before,
    abandoned uploads held their spooled files open behind one long registration)."""
    limiter = InferenceLimiter(1, 2, timeout_s=30.0)
    busy, freed = threading.Event(), []

    async def main() -> tuple[list[int], bool]:
        statuses = []
        with limiter.admit() as first:
            running = asyncio.ensure_future(first.run(busy.wait))
            await asyncio.sleep(0.1)
            for _ in range(2):
                upload = Upload()
                weakref.finalize(upload, freed.append, 1)

                async def route(held: Upload) -> int:
                    try:
                        with limiter.admit() as slot:
                            await slot.run(lambda: held, gone)
                    except ClientDisconnect:
                        return 499
                    return 200

                statuses.append(await route(upload))
                del upload
            await asyncio.sleep(0.05)  # the loop passes the cancellation on to the executor's future
            gc.collect()
            let_go = len(freed) == 2 and limiter.running == 1  # the worker still runs the first job
            busy.set()
            await running
        return statuses, let_go

    statuses, let_go = asyncio.run(main())
    limiter.shutdown()
    assert statuses == [499, 499] and let_go
