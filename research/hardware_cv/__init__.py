"""Hardware cross-validation experiments: frozen research scripts, not part of the ``dacr_learn`` library.

Their figures are in the docs (the dated sections of docs/history/hardware.md, and
docs/history/compositional.md, docs/history/results.md); each script's docstring names its section and its exact
command, ``python -m research.hardware_cv.<script> …`` from the repository root. They are not
maintained beyond running: kept so the documented numbers can be reproduced, not run by the tests.
Importing a script reads no data and writes nothing; the work happens in its ``main()``. A script runs
on the current library, so where a library default changed after its date, its numbers can differ from
the ones quoted then.
``common`` (the v4/v6 training set-up, a cached loader) and ``folds`` (proxy folds with the chosen
CC variant) are shared by the scripts; ``results/`` holds the outputs quoted in the docs.
See README.md here for the list of scripts, their options and run times.
"""
