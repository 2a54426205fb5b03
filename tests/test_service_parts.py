"""The daemon's parts on their own: each stops within its budget, whatever its task is doing."""

from __future__ import annotations

import asyncio
import logging
import time

import pytest

from companion.config import CompanionConfig
from companion.service.parts import TaskPart
from companion.service.presence import Presence


def _presence(link=None) -> Presence:
    return Presence(
        config=CompanionConfig,
        link=lambda: link,
        connected=lambda: True,
        state=lambda: "passive",
        engaged=lambda: False,
        clock=time.monotonic,
    )


def test_the_presence_task_stops_when_cancelled_as_it_is_woken() -> None:
    """The presence task once outlived the shutdown ("task presence did not stop within 2 s"): it
    waited with asyncio.wait_for, which before Python 3.12 swallows a cancellation that arrives in
    the same turn of the loop as the event it waits for."""

    async def main() -> bool:
        part = _presence()
        part.start()
        await asyncio.sleep(0.05)  # waiting for its next heartbeat
        part._wake.set()  # e.g. a STATUSTEXT queued by the last step before the shutdown
        return await part.stop(2.0)

    assert asyncio.run(main())


class _BlockedLink:
    """A link whose sends never return (a MAVSDK call blocked in its thread)."""

    def __init__(self) -> None:
        self.calls = 0

    async def send_heartbeat(self, state: int) -> None:
        self.calls += 1
        await asyncio.get_running_loop().create_future()  # never done


def test_a_send_that_never_returns_is_given_up_and_the_part_still_stops(caplog) -> None:
    caplog.set_level(logging.WARNING)

    async def main() -> tuple[bool, Presence, _BlockedLink]:
        link = _BlockedLink()
        part = _presence(link)
        part.start()
        deadline = time.monotonic() + 10.0
        while part.stats["send_errors"] < 1 and time.monotonic() < deadline:
            await asyncio.sleep(0.05)
        return await part.stop(1.0), part, link

    stopped, part, link = asyncio.run(main())
    assert stopped and part.stats["send_errors"] >= 1 and link.calls >= 1
    assert "HEARTBEAT not sent within" in caplog.text


class _Stubborn(TaskPart):
    name = "stubborn"

    async def run(self) -> None:
        while True:
            try:
                await asyncio.sleep(10.0)
            except asyncio.CancelledError:
                continue  # a bug: ignores its cancellation


def test_a_part_that_ignores_its_cancellation_is_left_after_its_budget(caplog) -> None:
    caplog.set_level(logging.ERROR)

    async def main() -> tuple[bool, float]:
        part = _Stubborn()
        part.start()
        await asyncio.sleep(0.01)
        t0 = time.monotonic()
        stopped = await part.stop(0.2)
        elapsed = time.monotonic() - t0
        return stopped, elapsed

    loop = asyncio.new_event_loop()
    try:
        stopped, elapsed = loop.run_until_complete(main())
    finally:
        for task in asyncio.all_tasks(loop):
            task.cancel()  # the stubborn one keeps running; let the loop go without it
        loop.close()
    assert not stopped and elapsed < 5.0
    assert "task stubborn did not stop within 0.2 s; leaving it" in caplog.text


def test_a_part_that_dies_is_reported() -> None:
    died: list[tuple[str, str]] = []

    class _Dying(TaskPart):
        name = "dying"

        async def run(self) -> None:
            raise RuntimeError("boom")

    async def main() -> None:
        part = _Dying(on_died=lambda name, err: died.append((name, str(err))))
        part.start()
        await asyncio.sleep(0.05)

    asyncio.run(main())
    assert died == [("dying", "boom")]


@pytest.mark.parametrize("budget_s", [0.5])
def test_a_stopped_part_stops_again_at_once(budget_s: float) -> None:
    async def main() -> tuple[bool, bool]:
        part = _presence()
        part.start()
        first = await part.stop(budget_s)
        return first, await part.stop(budget_s)

    assert asyncio.run(main()) == (True, True)
