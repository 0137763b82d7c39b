"""``python -m fsswarp`` runs the command line."""

from .cli import run

if __name__ == "__main__":  # a spawned child process imports this module as __mp_main__: it must not run
    run()
