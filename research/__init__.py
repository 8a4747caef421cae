"""Frozen research scripts behind figures in the docs (not part of the ``dacr_learn`` library).

Each script is run from the repository root as ``python -m research.<script>`` or
``python -m research.hardware_cv.<script>``; its docstring names the docs section whose numbers it
produced and its exact command. They are kept so those numbers can be reproduced: they are not
maintained beyond running, not installed with the package, and not run by the test suite (it only
imports each one: tests/test_research_imports.py).

- :mod:`research.ik_pose_loss`: docs/history/ablation.md, "Multi-segment IK with a pose loss"
- :mod:`research.hardware_analysis`: docs/history/hardware.md, "2026-11-21: Where the error comes from"
- :mod:`research.hardware_cv`: the hardware cross-validation rounds of docs/history/hardware.md
- :mod:`research.twist_head`: docs/history/compositional.md, "Twisting segments: the roll (2026-11-26)"
"""
