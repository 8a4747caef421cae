"""What a command-line entry point shows the user: nothing they cannot act on, and a mistake in
their files or arguments as one line.

    if __name__ == "__main__":
        sys.exit(run_cli(main))          # main(argv: list[str] | None) of the CLI

:func:`run_cli` installs :func:`quiet_third_party_warnings`, runs ``main`` and turns a user error
(a ``ValueError`` or ``FileNotFoundError`` anywhere in the raised exception's chain, the project's
own one preferred: :func:`first_user_error`) into the line ``error: <message>`` on stderr, exit
status 2, with no traceback (``DACR_DEBUG=1`` prints the traceback too). Ctrl-C is the line
``interrupted (Ctrl-C)``, status 130. Any other exception is a bug and propagates with its traceback.
"""
from __future__ import annotations

import logging
import os
import re
import sys
import traceback
import warnings
from collections.abc import Callable, Iterator

USER_ERRORS: tuple[type[Exception], ...] = (ValueError, FileNotFoundError)
"""The exception types that are a user's mistake (checks.py: a bad file or argument is a ValueError
naming it, a missing file a FileNotFoundError naming it)."""

DEBUG_ENV = "DACR_DEBUG"

# Each filter: (message regex, category, module regex of the code the warning is attributed to).
# The module is the one named in the warning's "file:line" (the caller, for a warning raised with
# stacklevel=2); matched to its end, so a filter hides that one warning from that one place.
_WARNINGS: tuple[tuple[str, type[Warning], str], ...] = (
    # torch 2.13 deprecates constructing torch.utils._pytree.LeafSpec (typing_extensions.deprecated,
    # attributed to the caller); Lightning 2.6's own pytree copy builds one for every batch it moves
    # (lightning/pytorch/utilities/_pytree.py:21, _tree_flatten). Lightning's to fix, not the user's.
    (r"`isinstance\(treespec, LeafSpec\)` is deprecated", FutureWarning,
     r"lightning\.pytorch\.utilities\._pytree\Z"),
    # The same deprecation when torch itself deep-copies an FX graph holding a LeafSpec:
    # torch/_dynamo/repro/after_aot.py (debug_wrapper: copy.deepcopy(gm.graph)) re-creates it through
    # copyreg.__newobj__, so the warning names copyreg.py:105. Raised by every AOTInductor compile
    # (python -m dacr_learn.export without --no-aoti).
    (r"`isinstance\(treespec, LeafSpec\)` is deprecated", FutureWarning, r"copyreg\Z"),
    # torch 2.13's Inductor reads a tensor's TypedStorage while it times the candidate kernels of a matrix
    # product (torch/_inductor/select_algorithm.py: out_base.storage()); only with max_autotune
    # (python -m dacr_learn.export --autotune).
    (r"TypedStorage is deprecated", UserWarning, r"torch\._inductor\.select_algorithm\Z"),
)

# Lightning's adverts, logged with rank_zero_info (INFO) on this logger, not warnings. Lightning 2.6
# has no flag or environment variable that turns them off; a filter on the logger drops exactly these
# records (logging.Logger filters see only the records logged on that logger).
_LIGHTNING_LOGGER = "lightning.pytorch.utilities.rank_zero"
_LIGHTNING_ADVERTS: tuple[re.Pattern[str], ...] = (
    # lightning/pytorch/trainer/connectors/logger_connector/logger_connector.py (any logger but LitLogger)
    re.compile(r"💡 Tip: For seamless cloud logging and experiment tracking, try installing \[litlogger\]"),
    # lightning/pytorch/trainer/connectors/callback_connector.py (the default ModelCheckpoint)
    re.compile(r"💡 Tip: For seamless cloud uploads and versioning, try installing \[litmodels\]"),
)


class _DropAdverts(logging.Filter):
    """Drops the log records of :data:`_LIGHTNING_ADVERTS`; every other record passes."""

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        return not any(p.match(message) for p in _LIGHTNING_ADVERTS)


_DROP_ADVERTS = _DropAdverts()


def quiet_third_party_warnings() -> None:
    """Hide the known third-party warnings and adverts a user of our CLIs cannot act on (each filter: one message
    from one module, :data:`_WARNINGS`, :data:`_LIGHTNING_ADVERTS`). Appended, so ``python -W …`` /
    ``PYTHONWARNINGS`` still decide; calling this again adds nothing."""
    for message, category, module in _WARNINGS:
        warnings.filterwarnings("ignore", message=message, category=category, module=module, append=True)
    logging.getLogger(_LIGHTNING_LOGGER).addFilter(_DROP_ADVERTS)   # addFilter skips a filter already there


def _raising_frame(err: BaseException):
    """The frame that raised ``err`` (the last of its traceback), or None."""
    return next(reversed([frame for frame, _ in traceback.walk_tb(err.__traceback__)]), None)


def _raised_by_us(err: BaseException) -> bool:
    """Whether ``err`` was raised in dacr_learn or in the script being run (``__main__``)."""
    frame = _raising_frame(err)
    name = frame.f_globals.get("__name__", "") if frame is not None else ""
    return name == "__main__" or name == "dacr_learn" or name.startswith("dacr_learn.")


def _union_alternatives(err: BaseException) -> list[BaseException]:
    """The errors of every Union member when jsonargparse gave up on a Union-typed value.

    jsonargparse 4.53 (``_typehints.raise_union_unexpected_value``) raises a new ``ValueError("Does not
    validate against any of the Union subtypes …")`` ``from exceptions[0]``: the first member's error
    is its ``__cause__``, the others only survive as the ``exceptions`` list in the raising frame."""
    frame = _raising_frame(err)
    if frame is None or not str(frame.f_globals.get("__name__", "")).startswith("jsonargparse"):
        return []
    found = frame.f_locals.get("exceptions")
    if not isinstance(found, list | tuple):
        return []
    return [e for e in found if isinstance(e, BaseException)]


def _chain(err: BaseException) -> Iterator[BaseException]:
    """``err`` and the exceptions behind it, outermost first: ``__cause__``, ``__context__`` (unless
    suppressed by ``raise … from``), and jsonargparse's Union alternatives; each once."""
    seen: set[int] = set()
    stack = [err]
    while stack:
        e = stack.pop()
        if id(e) in seen:
            continue
        seen.add(id(e))
        yield e
        behind = [e.__cause__, None if e.__suppress_context__ else e.__context__, *_union_alternatives(e)]
        stack.extend(reversed([b for b in behind if b is not None]))


def first_user_error(err: BaseException) -> ValueError | FileNotFoundError | None:
    """The user's mistake behind ``err``, or None when there is none (a bug): the outermost :data:`USER_ERRORS`
    instance in ``err``'s chain (:func:`_chain`) raised by our own code (dacr_learn, or the script run as
    ``__main__``), the one that names the file, so a library's wrapper is skipped (jsonargparse's "Does not validate
    against any of the Union subtypes …" around our ``ValueError("<robot.yaml>: segments[0]: …")``, argparse's
    ArgumentError); without one of ours, the outermost instance (e.g. re-raised from a worker process)."""
    errors = [e for e in _chain(err) if isinstance(e, USER_ERRORS)]
    return next((e for e in errors if _raised_by_us(e)), errors[0] if errors else None)


def debug_enabled() -> bool:
    """Whether ``DACR_DEBUG`` is set (to anything but empty or 0): tracebacks of user errors are shown."""
    return os.environ.get(DEBUG_ENV, "").strip() not in ("", "0")


def run_cli(main: Callable[[list[str] | None], object], argv: list[str] | None = None) -> int:
    """Run a CLI's ``main(argv)`` (``argv`` None: ``sys.argv[1:]``) and return its exit status (0, 2 for a user
    error, 130 for Ctrl-C; the module docstring)."""
    quiet_third_party_warnings()
    try:
        main(argv)
    except KeyboardInterrupt:
        sys.stdout.flush()
        print("\ninterrupted (Ctrl-C)", file=sys.stderr)
        return 130
    except Exception as err:
        user_error = first_user_error(err)
        if user_error is None:
            raise
        sys.stdout.flush()                      # what the command printed so far comes first
        if debug_enabled():
            traceback.print_exception(err)
        print(f"error: {str(user_error).strip() or type(user_error).__name__}", file=sys.stderr)
        return 2
    return 0
