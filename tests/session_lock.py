"""A readers-writer lock shared by the processes of one test session (pytest-xdist workers).

Ordinary tests hold it shared, so they run side by side on the workers; a test marked ``exclusive`` (a drive
served in real time, a master judging its answers) holds it exclusively, so it runs with no other test beside
it, as in a session without workers. A turnstile in front of the shared side keeps a waiting exclusive test
from being starved by a stream of ordinary ones: once it waits, no new ordinary test starts.
"""

from __future__ import annotations

import fcntl
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


class SessionLock:
    def __init__(self, folder: Path) -> None:
        self.turnstile_path = folder / "turnstile.lock"
        self.room_path = folder / "room.lock"

    @contextmanager
    def shared(self) -> Iterator[None]:
        with open(self.turnstile_path, "a") as turn, open(self.room_path, "a") as room:
            fcntl.flock(turn, fcntl.LOCK_EX)
            try:
                fcntl.flock(room, fcntl.LOCK_SH)
            finally:
                fcntl.flock(turn, fcntl.LOCK_UN)
            try:
                yield
            finally:
                fcntl.flock(room, fcntl.LOCK_UN)

    @contextmanager
    def exclusive(self) -> Iterator[None]:
        with open(self.turnstile_path, "a") as turn, open(self.room_path, "a") as room:
            fcntl.flock(turn, fcntl.LOCK_EX)
            try:
                fcntl.flock(room, fcntl.LOCK_EX)
                try:
                    yield
                finally:
                    fcntl.flock(room, fcntl.LOCK_UN)
            finally:
                fcntl.flock(turn, fcntl.LOCK_UN)
