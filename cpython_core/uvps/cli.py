"""Command-line interface: ``uvps``. (Skeleton; filled in by commands.py.)"""
import sys


def main(argv=None) -> int:
    from .commands import cli_main

    return cli_main(sys.argv[1:] if argv is None else list(argv))


if __name__ == "__main__":
    sys.exit(main())
