"""cadestate: CAD models placed in 3D in walkthrough videos (see README.md). The package's own
namespace holds only what every process of it shares: how it ends on SIGTERM."""

from __future__ import annotations


def exit_on_sigterm() -> None:
    """Make SIGTERM end this process as an exit (status 128 + 15) instead of killing it outright, so
    that ``finally`` blocks and exit handlers run (temporary files and folders removed, a Prefect API
    the process launched stopped), as on Ctrl-C. Only from the main thread, and only where SIGTERM
    has no handler yet. Here, not in a module: every command calls it, and it imports nothing first."""
    import signal
    import threading

    if threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
        signal.signal(signal.SIGTERM, _exit_on_signal)


def _exit_on_signal(signum: int, frame) -> None:
    raise SystemExit(128 + signum)


def quiet_exit() -> None:
    """Have SIGTERM and Ctrl-C ignored from when the exit handlers registered before this call
    start to run (the last registered runs first): a command that is done ends as it was ending
    (the Prefect API it launched stopped, up to 5 s), where a signal then printed a traceback
    ("Exception ignored in atexit callback ... SystemExit: 143"). Called when a command is done;
    called again, it goes before every handler registered since."""
    import atexit

    atexit.unregister(_ignore_ending_signals)
    atexit.register(_ignore_ending_signals)


def _ignore_ending_signals() -> None:
    import signal
    import threading

    if threading.current_thread() is threading.main_thread():
        for s in (signal.SIGINT, signal.SIGTERM):
            signal.signal(s, signal.SIG_IGN)
