"""``BodyBudget``: bodies held at once stay within its capacity, holds are granted in arrival order, and a request
that goes away while it waits gives its place back."""

from __future__ import annotations

import asyncio
import threading

import pytest

from service.api.body_budget import BodyBudget


async def settle() -> None:
    for _ in range(5):
        await asyncio.sleep(0)


def test_holds_wait_until_their_bytes_are_free_in_arrival_order():
    async def scenario() -> list[str]:
        budget = BodyBudget(100)
        order: list[str] = []
        first = await budget.hold(60)

        async def take(name: str, nbytes: int):
            hold = await budget.hold(nbytes)
            order.append(name)
            return hold

        large = asyncio.create_task(take("large", 90))
        await settle()
        small = asyncio.create_task(take("small", 10))  # fits now, but the large one asked first
        await settle()
        assert order == [] and budget.held == 60
        first.release()
        first.release()  # once only
        (await large).release()
        (await small).release()
        assert budget.held == 0
        return order

    assert asyncio.run(scenario()) == ["large", "small"]


def test_a_body_above_the_capacity_is_read_alone():
    async def scenario() -> None:
        budget = BodyBudget(100)
        with await budget.hold(500) as hold:
            assert hold.nbytes == 100 and budget.held == 100
        assert budget.held == 0

    asyncio.run(scenario())


def test_a_request_cancelled_while_waiting_gives_its_place_back():
    async def scenario() -> None:
        budget = BodyBudget(100)
        first = await budget.hold(100)
        gone = asyncio.create_task(budget.hold(80))
        behind = asyncio.create_task(budget.hold(20))
        await settle()
        gone.cancel()
        with pytest.raises(asyncio.CancelledError):
            await gone
        first.release()
        (await behind).release()
        assert budget.held == 0

    asyncio.run(scenario())


def test_a_grant_to_a_request_cancelled_before_it_resumes_is_given_back():
    async def scenario() -> None:
        budget = BodyBudget(100)
        first = await budget.hold(100)
        waiting = asyncio.create_task(budget.hold(100))
        await settle()
        first.release()  # grants the waiting hold; the task has not resumed yet
        waiting.cancel()
        with pytest.raises(asyncio.CancelledError):
            await waiting
        assert budget.held == 0

    asyncio.run(scenario())


def test_released_from_a_worker_thread():
    async def scenario() -> None:
        budget = BodyBudget(100)
        first = await budget.hold(100)
        waiting = asyncio.create_task(budget.hold(50))
        await settle()
        threading.Thread(target=first.release).start()  # as a registration's decode does
        (await asyncio.wait_for(waiting, 5)).release()
        assert budget.held == 0

    asyncio.run(scenario())
