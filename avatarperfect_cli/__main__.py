"""Entry point of `avatarperfect` and `python -m avatarperfect_cli`.

Ctrl-C and SIGTERM are routed to `interrupts` first, so a signal during the start-up imports also ends
in "interrupted" and status 130. A command that writes a workspace another stage holds is refused before
the CLI's heavy imports (torch and numba take seconds to load), with the line the lock itself gives; the
lock stays the authority.
"""

from __future__ import annotations

import sys
from pathlib import Path

# commands that take the workspace lock; any of their positional arguments may name the workspace
# apply-edit --list reads the workspace without needing its lock, and evaluate scores a committed avatar without it
READ_ONLY_OPTION = "--list"
LOCKING_COMMANDS = frozenset(
    {"train-initial", "visibility", "suggest", "apply-edit", "refine", "simulate-user", "report", "loop", "relink"}
)


def main() -> None:
    from avatarperfect_cli import interrupts

    interrupts.install()
    try:
        refuse_busy_workspace(sys.argv[1:])
        from avatarperfect_cli.cli import app

        app(prog_name="avatarperfect")
    except KeyboardInterrupt:  # before or after a command (the commands report their own)
        print("interrupted: nothing was changed", file=sys.stderr)
        raise SystemExit(130) from None
    finally:
        interrupts.finish()


def refuse_busy_workspace(argv: list[str]) -> None:
    """Exit with status 2 and one line when `argv` runs a locking command on a busy workspace."""
    if not argv or argv[0] not in LOCKING_COMMANDS or READ_ONLY_OPTION in argv:
        return
    from avatarperfect_cli.errors import AvatarPerfectError
    from avatarperfect_cli.io.workspace import refuse_if_busy

    try:
        for argument in argv[1:]:
            if not argument.startswith("-"):
                refuse_if_busy(Path(argument))
    except AvatarPerfectError as error:
        print(f"error: {error}", file=sys.stderr)
        raise SystemExit(2) from None


if __name__ == "__main__":
    main()
