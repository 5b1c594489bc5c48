"""``python -m endogsim``: the ``endogsim`` command line."""

from endogsim.cli.main import app

app(prog_name="endogsim")
