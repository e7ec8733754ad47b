"""A lock shared by the processes of one test session (the pytest-xdist workers).

A test marked ``exclusive`` (a drive served in real time, a master judging its answers) holds it exclusively, so
no two such tests run at once on different workers. The shared side (with a turnstile in front of it, so a waiting
exclusive holder is not starved by a stream of shared ones) is there for tests that must run with no exclusive
test beside them.
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
