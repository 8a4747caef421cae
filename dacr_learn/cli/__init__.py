"""The command lines, above the library: each module has ``main(argv: list[str] | None = None)``, run by the
thin ``__main__`` of the package a user names (``python -m dacr_learn.<package>`` through
:func:`dacr_learn.console.run_cli`: a user error is one ``error: …`` line and exit status 2).

- :mod:`.plan`   ``python -m dacr_learn.plan ftl``: follow-the-leader insertion along a path

Nothing in the library imports this package.
"""
