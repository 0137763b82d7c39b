"""``python -m fsswarp`` runs the command line."""

from .cli import main

if __name__ == "__main__":  # a spawned child process imports this module as __mp_main__: it must not run
    raise SystemExit(main())
