"""The JSON form shared by the per-channel fields (:class:`vigproc.core.colour.ColourField`,
:class:`vigproc.core.gridfield.GridField`): a schema tag, the frame's size, the field's
own arrays, an optional 1-σ array of the same shape and an optional source."""

from __future__ import annotations

from typing import Any, Sequence

from vigproc.errors import ModelError


def field_to_dict(schema: str, width: int, height: int, body: dict[str, Any], sigma: Any = None,
                  source: str = "") -> dict[str, Any]:
    """The mapping of a field: ``schema``, ``width``, ``height``, then ``body``'s entries,
    ``sigma`` (a NumPy array, when known) and ``source`` (when not empty).

    Parameters
    ----------
    schema : str
    width, height : int
    body : dict
        The field's own entries, JSON-able.
    sigma : ndarray or None
    source : str

    Returns
    -------
    dict
    """
    d: dict[str, Any] = {"schema": schema, "width": width, "height": height, **body}
    if sigma is not None:
        d["sigma"] = sigma.tolist()
    if source:
        d["source"] = source
    return d


def check_field_dict(d: Any, what: str, schema: str, required: Sequence[str], *,
                     schema_optional: bool = False) -> tuple[Any, str]:
    """Check a field's mapping before it is built: an object, of ``schema``, with every
    ``required`` entry.

    Parameters
    ----------
    d : any
        The decoded JSON value.
    what : str
        The field's name in messages ("colour field").
    schema : str
        The schema this reader knows.
    required : sequence of str
    schema_optional : bool
        A mapping without ``schema`` is read as ``schema`` (files written before the tag).

    Returns
    -------
    (sigma, source)
        ``sigma`` as stored (None when absent) and ``source`` as a string.

    Raises
    ------
    ModelError
        Not an object, another schema, or a required entry missing.
    """
    if not isinstance(d, dict):
        raise ModelError(f"a {what} must be a JSON object")
    got = d.get("schema", schema if schema_optional else None)
    if got != schema:
        raise ModelError(f"unknown {what} schema {d.get('schema')!r} (expected {schema!r})")
    missing = [k for k in required if k not in d]
    if missing:
        raise ModelError(f"{what} is missing {missing[0]!r}")
    return d.get("sigma"), str(d.get("source", ""))
