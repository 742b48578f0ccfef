"""``python -m safelane.cli``: the ``safelane`` command line."""

from safelane.cli import app

if __name__ == "__main__":  # pragma: no cover
    app()
