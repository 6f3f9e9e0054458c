"""The networked processes' event loop (transport.event_loop): uvloop where installed,
asyncio's own on request, a clear error for a bad choice."""

import asyncio
import sys
import warnings

import pytest

from estimation.errors import RSEError
from transport import event_loop
from transport.event_loop import loop_name, run


async def _loop_module() -> str:
    await asyncio.sleep(0)
    return type(asyncio.get_running_loop()).__module__.partition(".")[0]


def test_uvloop_by_default(monkeypatch):
    uvloop = pytest.importorskip("uvloop", reason="uvloop is not installed (a dependency on Linux and macOS)")
    monkeypatch.delenv(event_loop.ENV, raising=False)
    assert run(_loop_module()) == "uvloop"
    assert loop_name() == f"uvloop {uvloop.__version__}"


@pytest.mark.parametrize("value", ["asyncio", " AsyncIO "])
def test_asyncio_on_request(monkeypatch, value):
    monkeypatch.setenv(event_loop.ENV, value)
    assert run(_loop_module()) == "asyncio"
    assert loop_name() == "asyncio"


def test_asyncio_when_uvloop_is_absent(monkeypatch):
    monkeypatch.delenv(event_loop.ENV, raising=False)
    monkeypatch.setitem(sys.modules, "uvloop", None)  # import uvloop raises ImportError
    assert run(_loop_module()) == "asyncio"
    monkeypatch.setenv(event_loop.ENV, "uvloop")
    with pytest.raises(RSEError, match=r"RSE_EVENT_LOOP=uvloop but uvloop is not installed"):
        run(_loop_module())


def test_a_bad_choice_is_one_error_and_the_coroutine_is_closed(monkeypatch):
    monkeypatch.setenv(event_loop.ENV, "trio")
    coro = _loop_module()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # "coroutine ... was never awaited" would be a warning
        with pytest.raises(RSEError, match=r"^RSE_EVENT_LOOP='trio': expected one of uvloop, asyncio$"):
            run(coro)
    assert coro.cr_frame is None  # closed


def test_signal_handlers_and_threadsafe_calls_on_the_chosen_loop(monkeypatch):
    """What the roles use of the loop: a signal handler, a call from another thread, a timer."""
    import os
    import signal
    import threading

    pytest.importorskip("uvloop", reason="uvloop is not installed (a dependency on Linux and macOS)")
    monkeypatch.delenv(event_loop.ENV, raising=False)

    async def main() -> list[str]:
        loop = asyncio.get_running_loop()
        got: list[str] = []
        done = asyncio.Event()
        loop.add_signal_handler(signal.SIGUSR1, lambda: got.append("signal"))
        try:
            threading.Thread(target=lambda: loop.call_soon_threadsafe(got.append, "thread")).start()
            loop.call_later(0.01, lambda: (got.append("timer"), done.set()))
            os.kill(os.getpid(), signal.SIGUSR1)
            await asyncio.wait_for(done.wait(), 5)
            await asyncio.sleep(0.01)
        finally:
            loop.remove_signal_handler(signal.SIGUSR1)
        return got

    assert sorted(run(main())) == ["signal", "thread", "timer"]
