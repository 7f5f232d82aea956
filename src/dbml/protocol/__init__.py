"""The wire schema: parameters, names, keys, message metadata and messages, written once for all."""

from dbml.protocol import keys, messages, metadata, names, schema
from dbml.protocol.schema import PARAMETERS, ParamError, Parameter, Scope, Writer, check_param

__all__ = [
    "PARAMETERS",
    "ParamError",
    "Parameter",
    "Scope",
    "Writer",
    "check_param",
    "keys",
    "messages",
    "metadata",
    "names",
    "schema",
]
