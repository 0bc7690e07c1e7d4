"""The lab: freeform's research beside the library — the control and co-design studies' commands (``python -m
lab.<name>``), their result folders (``lab/results/``), the notebook of what was tried (``lab/notes/``) and the
record of the control research (``lab/control-research.md``). Nothing in ``freeform/`` imports it."""
