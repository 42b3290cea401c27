"""Running a piece of a test as another user (root-only cases: root ignores file modes)."""
from __future__ import annotations

import os

NOBODY = 65534  # the unprivileged user the root-only cases become


def as_nobody(action, refused: type[BaseException]) -> str:
    """Run `action` in a child process that became user nobody: the message of the `refused` it raised, or 'ok'."""
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: only this, then _exit
        try:
            os.setgid(NOBODY)
            os.setuid(NOBODY)
            try:
                action()
                answer = "ok"
            except refused as exc:
                answer = str(exc)
            os.write(write, answer.encode())
        finally:
            os._exit(0)
    os.close(write)
    with os.fdopen(read, "rb") as pipe:
        answer = pipe.read().decode()
    os.waitpid(pid, 0)
    return answer
