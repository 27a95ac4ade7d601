"""The ``vt-edge`` command (``python -m edge``). Its first instruction holds SIGHUP and SIGTERM
for ``vt-edge run``, before the command line's modules are imported (about a second on a busy
host): one sent while the daemon starts is never fatal (edge/runtime/signals.py)."""

import sys

from edge.runtime import signals


def main() -> int:
    signals.hold_if_daemon(sys.argv[1:])
    from edge.cli import main as cli_main  # after the hold: importing it takes the time

    return cli_main()


if __name__ == "__main__":
    sys.exit(main())
