"""The fleet from ``dbml secure init``'s flags: ``r1,r2``, ``NAME=ENDPOINT``, ``[NAME=]SAN``."""

from __future__ import annotations

from collections.abc import Sequence

from dbml.secure.fleet import DEFAULT_BASE_PORT, Fleet, SecureError, plan_fleet

__all__ = ["fleet_from_flags"]


def _split_names(field: str, text: str) -> list[str]:
    """``"r1,r2"`` as names; an empty text is no name, an empty item is an error."""
    if not text.strip():
        return []
    names = [item.strip() for item in text.split(",")]
    for name in names:
        if not name:
            raise SecureError(f"{field}={text!r} has an empty name")
    return names


def _split_assignment(field: str, item: str) -> tuple[str, str]:
    name, sep, value = item.partition("=")
    if not sep or not name.strip() or not value.strip():
        raise SecureError(f"{field}={item!r} must look like NAME=VALUE")
    return name.strip(), value.strip()


def fleet_from_flags(
    *,
    optimizer: str,
    robots: str,
    operators: str = "",
    endpoints: Sequence[str] = (),
    sans: Sequence[str] = (),
    base_port: int = DEFAULT_BASE_PORT,
) -> Fleet:
    """The fleet from the command line's text: ``r1,r2``, ``NAME=ENDPOINT``, ``[NAME=]SAN``."""
    by_node: dict[str, str] = {}
    for item in endpoints:
        name, endpoint = _split_assignment("--endpoint", item)
        if name in by_node:
            raise SecureError(f"--endpoint {item!r}: {name!r} has an endpoint already")
        by_node[name] = endpoint
    common: list[str] = []
    node_sans: dict[str, list[str]] = {}
    for item in sans:
        if "=" in item:
            name, value = _split_assignment("--san", item)
            node_sans.setdefault(name, []).append(value)
        else:
            common.append(item)
    return plan_fleet(
        optimizer=optimizer,
        robots=_split_names("--robots", robots),
        operators=_split_names("--operators", operators),
        endpoints=by_node,
        sans=common,
        node_sans=node_sans,
        base_port=base_port,
    )
