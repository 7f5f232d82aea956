"""The wire schema: parameters, names, keys and message metadata, written once for all."""

from dbml.protocol import keys, metadata, names, schema
from dbml.protocol.schema import PARAMETERS, ParamError, Parameter, Scope, Writer, check_param

__all__ = [
    "PARAMETERS",
    "ParamError",
    "Parameter",
    "Scope",
    "Writer",
    "check_param",
    "keys",
    "metadata",
    "names",
    "schema",
]
