"""Groups of compared rows, each drawn as its own learning-curve figure (the spec's Figs. 7-13 show one
family of methods per figure: RL, safe RL, offline/IL, RLHF).

A group spec is ``NAME=LABEL,LABEL,...``: NAME (letters, digits, ``-``, ``_``) names the file
``learning_curves_<NAME>.png``; the labels are rows of the comparison (as ``--row``/``--eval``/``--glob``
labelled them). Every evaluation-only row (IDM-MOBIL) joins each group as its reference level.
"""

from __future__ import annotations

import re

from pe_rlhf.apps.compare.rows import TRAINED, CompareError, Row

_NAME = re.compile(r"[A-Za-z0-9_-]+")


def parse_group(spec: str) -> tuple[str, list[str]]:
    """``"rl=SAC-RS,PPO-RS"`` -> ``("rl", ["SAC-RS", "PPO-RS"])``; CompareError naming the bad spec."""
    name, sep, labels = spec.partition("=")
    name = name.strip()
    members = [label.strip() for label in labels.split(",") if label.strip()]
    if not sep or not _NAME.fullmatch(name) or not members:
        raise CompareError(f"--group {spec!r}: expected NAME=LABEL[,LABEL...] with NAME of letters, digits, - or _")
    return name, members


def select_group(rows: list[Row], labels: list[str]) -> list[Row]:
    """The rows labelled ``labels`` (in the table's order), after every evaluation-only row; CompareError
    naming the labels no row carries."""
    known = {row.label for row in rows}
    unknown = [label for label in labels if label not in known]
    if unknown:
        raise CompareError(f"--group: no row labelled {', '.join(map(repr, unknown))}; rows: "
                           f"{', '.join(row.label for row in rows)}")
    wanted = set(labels)
    return [row for row in rows if row.kind != TRAINED] + [row for row in rows if row.label in wanted
                                                           and row.kind == TRAINED]


def group_png(name: str) -> str:
    """The file a group's figure is written to."""
    return f"learning_curves_{name}.png"
