"""Save and load CBNs (structure + CPTs) in standard formats.

The format follows the file suffix:

* ``.xmlbif`` / ``.xml``: XMLBIF 0.3 through pgmpy's ``XMLBIFWriter`` /
  ``XMLBIFReader`` (readable by pgmpy, Weka, SamIam and other BN tools);
  values are written with full float precision, so a round trip is exact;
* ``.json``: a plain JSON document ``{"format": "torchrl_causal.cbn/1",
  "nodes": {name: {"states": [...], "parents": [...], "cpt": [[...]]}}, ...}``
  with the CPT in pgmpy's ``TabularCPD`` layout (rows = states of the node,
  columns = parent configurations, first parent slowest). No pgmpy needed to read it.

State names are the schema's category labels; the ``known`` flag and the
number of rows are kept in the JSON document (and in the learner's
``learner.json`` for XMLBIF).

:func:`load_cbn_folder` reads a whole folder of them, one file per action, as
:meth:`~torchrl_causal.causal.CausalLearner.save` writes it (the input of
:meth:`~torchrl_causal.causal.CausalLearner.transfer`).

Example:
    >>> import tempfile, os, numpy as np
    >>> from torchrl_causal.causal.inference import fit_cbn
    >>> from torchrl_causal.causal.io import save_cbn, load_cbn
    >>> cbn = fit_cbn([("altitude_t", "altitude_t1")], np.zeros((4, 19), dtype=int))
    >>> path = os.path.join(tempfile.mkdtemp(), "ascend.json")
    >>> _ = save_cbn(cbn, path)
    >>> load_cbn(path).edges
    [('altitude_t', 'altitude_t1')]
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from torchrl_causal.causal.inference import CBN
from torchrl_causal.schema import DEFAULT_SCHEMA, VariableSchema

__all__ = ["save_cbn", "load_cbn", "load_cbn_folder", "FORMATS"]

FORMATS = (".xmlbif", ".xml", ".json")
JSON_FORMAT = "torchrl_causal.cbn/1"


def _suffix(path) -> str:
    suffix = Path(path).suffix.lower()
    if suffix not in FORMATS:
        raise ValueError(f"path suffix must be one of {FORMATS}, got {str(path)!r}")
    return suffix


def save_cbn(cbn: CBN, path: str | os.PathLike) -> Path:
    """Write ``cbn`` to ``path`` in the format of its suffix.

    Args:
        cbn: the network.
        path: target file (``.xmlbif``, ``.xml`` or ``.json``).

    Returns:
        the path written.

    Example:
        >>> import tempfile, os
        >>> from torchrl_causal.causal import expert_dags
        >>> from torchrl_causal.causal.inference import fit_cbn, random_cbn
        >>> from torchrl_causal.schema import DEFAULT_SCHEMA
        >>> data = random_cbn(expert_dags()["forward"], seed=0).sample(500, seed=1)
        >>> cbn = fit_cbn(expert_dags()["forward"], data, DEFAULT_SCHEMA)
        >>> path = save_cbn(cbn, os.path.join(tempfile.mkdtemp(), "forward.json"))
        >>> sorted(load_cbn(path).edges) == sorted(cbn.edges)
        True
    """
    suffix = _suffix(path)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".json":
        labels = cbn.schema.node_labels()
        doc = {
            "format": JSON_FORMAT,
            "known": cbn.known,
            "n_rows": cbn.n_rows,
            "prior": cbn.prior,
            "meta": cbn.meta,
            "edges": [list(e) for e in cbn.edges],
            "nodes": {
                n: {
                    "states": labels[n],
                    "parents": list(cbn.parents[n]),
                    "cpt": np.asarray(cbn.cpts[n]).tolist(),
                }
                for n in cbn.schema.node_names()
            },
        }
        path.write_text(json.dumps(doc, indent=1))
        return path
    from pgmpy.readwrite import XMLBIFWriter

    XMLBIFWriter(cbn.to_pgmpy()).write(str(path))
    return path


def load_cbn(path: str | os.PathLike, schema: VariableSchema = DEFAULT_SCHEMA) -> CBN:
    """Read a CBN written by :func:`save_cbn` (or any XMLBIF file over the schema's nodes).

    Args:
        path: the file.
        schema: the variable schema its nodes and states follow.

    Returns:
        :class:`~torchrl_causal.causal.inference.CBN`.

    Example:
        >>> import tempfile, os
        >>> from torchrl_causal.causal import expert_dags
        >>> from torchrl_causal.causal.inference import random_cbn
        >>> cbn = random_cbn(expert_dags()["ascend"], seed=0)
        >>> path = save_cbn(cbn, os.path.join(tempfile.mkdtemp(), "ascend.xmlbif"))
        >>> len(load_cbn(path).edges) == len(cbn.edges)
        True
    """
    suffix = _suffix(path)
    if suffix == ".json":
        doc = json.loads(Path(path).read_text())
        if doc.get("format") != JSON_FORMAT:
            raise ValueError(f"{path} is not a {JSON_FORMAT} document")
        labels = schema.node_labels()
        nodes = schema.node_names()
        if set(doc["nodes"]) != set(nodes):
            raise ValueError(f"{path}: nodes do not match the schema's {nodes}")
        parents, cpts = {}, {}
        for n in nodes:
            spec = doc["nodes"][n]
            if spec["states"] != labels[n]:
                raise ValueError(f"{path}: states of {n} {spec['states']} != schema {labels[n]}")
            parents[n] = tuple(spec["parents"])
            cpts[n] = np.asarray(spec["cpt"], dtype=np.float64)
        edges = [(u, v) for v in nodes for u in parents[v]]
        return CBN(edges, cpts, parents, schema, int(doc.get("n_rows", 0)), bool(doc.get("known", True)),
                   float(doc.get("prior", 1.0)), dict(doc.get("meta", {})))
    from pgmpy.readwrite import XMLBIFReader

    return CBN.from_pgmpy(XMLBIFReader(str(path)).get_model(), schema)


def load_cbn_folder(
    directory: str | os.PathLike,
    schema: VariableSchema = DEFAULT_SCHEMA,
    action_names: Sequence[str] | None = None,
) -> dict[str, CBN]:
    """Read a folder of CBNs, one file ``<action><suffix>`` per action.

    The folder :meth:`~torchrl_causal.causal.CausalLearner.save` writes
    (``<run>/cbns/last`` of a training run), or any folder of XMLBIF / JSON
    files over the schema's nodes. The ``known`` flag and the row count of each
    CBN come from the folder's ``learner.json`` when it has one; without it an
    XMLBIF CBN counts as known.

    Args:
        directory: the folder.
        schema: the variable schema every file's nodes and states must follow.
        action_names: the actions that need a file (``None``: every file is read).

    Returns:
        ``{action_name: CBN}``, in ``action_names`` order when given.

    Raises:
        ValueError: naming the folder or file: the folder does not exist; it
            holds no CBN file; a file's variables or states are not the schema's
            (CBNs of another env); two files for one action; a file for an
            action not in ``action_names``, or an action without a file.

    Example:
        >>> import tempfile
        >>> from torchrl_causal.causal import CausalLearner
        >>> folder = CausalLearner().save(tempfile.mkdtemp())
        >>> cbns = load_cbn_folder(folder)
        >>> len(cbns), cbns["forward"].known
        (8, False)
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise ValueError(f"{str(directory)!r} is not an existing folder")
    files = sorted(p for p in directory.iterdir()
                   if p.is_file() and p.suffix.lower() in FORMATS and p.name != "learner.json")
    if not files:
        raise ValueError(f"{str(directory)!r} holds no CBN file (*.xmlbif, *.xml or *.json)")
    summary = directory / "learner.json"
    meta = json.loads(summary.read_text()).get("actions", {}) if summary.is_file() else {}
    cbns: dict[str, CBN] = {}
    for path in files:
        try:
            cbn = load_cbn(path, schema)
        except Exception as err:  # pgmpy parse errors, node / state mismatches
            raise ValueError(
                f"{str(path)!r} is not a CBN over the schema's variables {schema.node_names()} "
                f"({type(err).__name__}: {err}); was it saved for another env or schema?"
            ) from None
        if path.stem in cbns:
            raise ValueError(f"{str(directory)!r} holds two CBN files for {path.stem!r}")
        info = meta.get(path.stem, {})
        cbn.known = bool(info.get("known", cbn.known))
        cbn.n_rows = int(info.get("n_rows", cbn.n_rows))
        cbns[path.stem] = cbn
    if action_names is None:
        return cbns
    names = list(action_names)
    missing = [n for n in names if n not in cbns]
    extra = [n for n in cbns if n not in names]
    if missing or extra:
        raise ValueError(
            f"{str(directory)!r} must hold one CBN file per action {names}; "
            f"missing: {missing}, unknown: {extra}"
        )
    return {n: cbns[n] for n in names}
