"""The wire schema: parameters, names and keys, written once for every transport and tool."""

from dbml.protocol import keys, names, schema
from dbml.protocol.schema import PARAMETERS, ParamError, Parameter, Scope, Writer, check_param

__all__ = [
    "PARAMETERS",
    "ParamError",
    "Parameter",
    "Scope",
    "Writer",
    "check_param",
    "keys",
    "names",
    "schema",
]
