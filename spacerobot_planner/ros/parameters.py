"""
Which node declares which parameter, and their ROS descriptors.

The schema (type, default, unit, range) is ``config.PARAMETERS``; here: the planner
declares everything it reads (``PLANNER_PARAMETERS``: not the CLI's ``scenario.*`` nor
the mock arm's), the mock arm the robot, its start posture and ``rate_hz``.  Strings
with a fixed set of values carry them in the descriptor's ``additional_constraints``
(rclpy has no field for them) and are checked by the node's own callback.
"""

from __future__ import annotations

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType
from rclpy.parameter import Parameter

from ..config import PARAMETERS, ROS_PARAMETERS, check_value

__all__ = ["PLANNER_PARAMETERS", "MOCK_ARM_PARAMETERS", "descriptor_for", "params_to_overrides",
           "check_choice", "CHOICES", "declare_checked", "as_declared", "ROS_PARAMETERS"]

_PTYPE = {
    "double": ParameterType.PARAMETER_DOUBLE, "integer": ParameterType.PARAMETER_INTEGER,
    "string": ParameterType.PARAMETER_STRING, "bool": ParameterType.PARAMETER_BOOL,
    "double_array": ParameterType.PARAMETER_DOUBLE_ARRAY,
    "integer_array": ParameterType.PARAMETER_INTEGER_ARRAY,
    "string_array": ParameterType.PARAMETER_STRING_ARRAY,
    "bool_array": ParameterType.PARAMETER_BOOL_ARRAY,
}
SPECS = {p.name: p for p in PARAMETERS}

#: the planner node's parameters (names as declared)
PLANNER_PARAMETERS = tuple(p.name for p in PARAMETERS
                           if not p.name.startswith(("scenario.", "mock_arm.")))
#: the mock arm's: declared name -> config.PARAMETERS name
MOCK_ARM_PARAMETERS = {**{p.name: p.name for p in PARAMETERS if p.name.startswith("robot.")},
                       "scenario.start_deg": "scenario.start_deg", "controller.switch": "controller.switch",
                       "rate_hz": "mock_arm.rate_hz",
                       "allow_trajectory_replacement": "mock_arm.allow_trajectory_replacement"}


def _solvers():
    from ..field import SOLVERS
    return tuple(SOLVERS)


def _acs_modes():
    from ..spacecraft import ACS_MODES
    return tuple(ACS_MODES)


def _controller_switches():
    from ..settings import CONTROLLER_SWITCHES
    return tuple(CONTROLLER_SWITCHES)


#: string parameters with a fixed set of values: name -> callable returning them
CHOICES = {"planner.solver": _solvers, "acs.mode": _acs_modes, "controller.switch": _controller_switches}


def check_choice(name: str, value) -> None:
    """Raise ValueError naming the parameter and the allowed values when ``value`` is not one."""
    allowed = CHOICES.get(name)
    if allowed is not None and value not in allowed():
        raise ValueError(f"{name}: {value!r} is not one of {', '.join(allowed())}")


def descriptor_for(spec, name: str | None = None) -> ParameterDescriptor:
    """Build the ParameterDescriptor of one ParamSpec: type, description, range, allowed values, read-only."""
    name = name or spec.name
    rng = ""
    if spec.min_value is not None or spec.max_value is not None:
        per = " per element." if spec.type.endswith("_array") else "."
        rng = f" Range [{spec.min_value}, {spec.max_value}]{per}"
    d = ParameterDescriptor(name=name, type=_PTYPE[spec.type], description=spec.description + rng,
                            read_only=spec.read_only)
    if spec.name in CHOICES:
        d.additional_constraints = "one of: " + ", ".join(CHOICES[spec.name]())
    elif spec.type.endswith("_array") and rng:
        d.additional_constraints = rng.strip()        # rclpy ranges apply to scalars only
    if spec.min_value is not None and spec.max_value is not None:
        if spec.type == "double":
            d.floating_point_range = [FloatingPointRange(from_value=float(spec.min_value),
                                                         to_value=float(spec.max_value), step=0.0)]
        elif spec.type == "integer":
            d.integer_range = [IntegerRange(from_value=int(spec.min_value), to_value=int(spec.max_value),
                                            step=0)]
    return d


_ROS_PREFIXES = ("qos_overrides.",)


def _normalise(spec, value):
    """Return a checked value in the type rclpy declares (an integer given for a double: a float)."""
    value = check_value(spec.name, value)
    if spec.type == "double_array":
        return [float(x) for x in value]
    if spec.type == "double":
        return float(value)
    return value


def as_declared(parameters, names: dict | None = None) -> list:
    """
    Return ``parameters`` (rclpy Parameters) with a whole number given for a double as a double.

    ``ros2 param set /spacerobot_planner safety_margin_m 1`` sends an integer, and ``[90, 180]``
    an integer array: for a double (array) of the schema they become the double (array) the
    parameter is declared with (as :func:`_normalise` does with start values), where rclpy
    would refuse them with enum numbers.  Everything else is passed on as it is.  ``names``:
    declared name -> schema name where they differ (``MOCK_ARM_PARAMETERS``: ``rate_hz``).
    """
    out = []
    for p in parameters:
        spec = SPECS.get(p.name if names is None else names.get(p.name, p.name))
        kind = None if spec is None else spec.type
        if kind == "double" and p.type_ == Parameter.Type.INTEGER:
            p = Parameter(p.name, Parameter.Type.DOUBLE, float(p.value))
        elif kind == "double_array" and p.type_ == Parameter.Type.INTEGER_ARRAY:
            p = Parameter(p.name, Parameter.Type.DOUBLE_ARRAY, [float(v) for v in p.value])
        out.append(p)
    return out


def declare_checked(node, names, specs: dict | None = None) -> dict:
    """
    Declare ``names`` on ``node`` with their descriptors; check start values first.

    The node must be made with ``automatically_declare_parameters_from_overrides=True``:
    what a parameter file, ``-p`` or ``parameter_overrides`` gave is then declared (without
    descriptor), read here, undeclared, checked with :func:`config.check_value` (a
    ValueError names the parameter and says why, before rclpy's descriptor checks, whose
    messages are about types and ranges only) and declared again with its descriptor.
    ``names``: declared name -> schema name (or an iterable of schema names).  Returns the
    values given at start that are not among ``names``, by name (another node's, or
    unknown: ``config.unknown_parameters``); they are undeclared.
    """
    names = dict(names) if isinstance(names, dict) else {n: n for n in names}
    specs = SPECS if specs is None else specs
    given = {}
    for name in node.list_parameters([], 0).names:
        if name in ROS_PARAMETERS or name.startswith(_ROS_PREFIXES):
            continue
        given[name] = node.get_parameter(name).value
        node.undeclare_parameter(name)
    for decl, schema in names.items():
        spec = specs[schema]
        value = spec.default
        if decl in given:
            value = _normalise(spec, given.pop(decl))
            check_choice(schema, value)
        node.declare_parameter(decl, value, descriptor_for(spec, decl), ignore_override=True)
    return given


def params_to_overrides(flat: dict, names: dict | None = None) -> list:
    """
    Convert a flat dotted dict (e.g. from ``config.load_params_file``) → rclpy Parameter list.

    ``names``: declared name -> schema name (e.g. ``MOCK_ARM_PARAMETERS``); by default
    every key is passed under its own name.  Values are type-checked and normalised.
    """
    out = []
    if names is None:
        items = [(k, k, v) for k, v in flat.items()]
    else:
        items = [(decl, schema, flat[schema] if schema in flat else flat[decl])
                 for decl, schema in names.items() if schema in flat or decl in flat]
    for decl, schema, v in items:
        spec = SPECS.get(schema)
        if spec is not None:
            v = check_value(schema, v)
            if spec.type == "double_array":
                v = [float(x) for x in v]
            elif spec.type == "double":
                v = float(v)
        out.append(Parameter(decl, value=v))
    return out
