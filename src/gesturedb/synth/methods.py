"""The registry of synthesis methods: the one list the CLI, the evaluation and the live server read.

    from gesturedb.synth import methods
    methods.names()                 # ("knn", "graph")
    m = methods.get("graph")        # a gesturedb.synth.protocol.Method
    result = m.open(db).synthesize("speech.wav", options=m.options(gap_s="auto"))

A new method is its own module (a synthesizer and its :class:`~gesturedb.synth.protocol.Method`
entry, ``METHOD``) plus its line in :data:`BUILTIN` below; code outside the package
can :func:`register` one at run time.
"""
from __future__ import annotations

from gesturedb.errors import ParameterError
from gesturedb.synth import graph, matching
from gesturedb.synth.protocol import EvalSystem, Method

__all__ = ["BUILTIN", "register", "get", "names", "all_methods", "eval_systems", "system_method"]

#: The methods that come with gesturedb, in the order they are listed (the first is the default).
BUILTIN = (
    matching.METHOD,
    graph.METHOD,
)

_REGISTRY: dict[str, Method] = {}


def register(method: Method, *, replace: bool = False) -> Method:
    """Add a method to the registry (a name already there is an error unless ``replace``)."""
    if not isinstance(method, Method):
        raise ParameterError(f"method: expected a gesturedb.synth.protocol.Method, got {type(method).__name__}")
    if method.name in _REGISTRY and not replace:
        raise ParameterError(f"method: {method.name!r} is already registered")
    taken = {s.name for m in _REGISTRY.values() if m.name != method.name for s in m.systems}
    clash = sorted(taken & {s.name for s in method.systems})
    if clash:
        raise ParameterError(f"method {method.name!r}: evaluation system names {clash} are another method's")
    _REGISTRY[method.name] = method
    return method


for _m in BUILTIN:
    register(_m)


def names() -> tuple[str, ...]:
    """Names of the registered methods, the default first."""
    return tuple(_REGISTRY)


def all_methods() -> tuple[Method, ...]:
    return tuple(_REGISTRY.values())


def get(name: str) -> Method:
    """The registered method called ``name``; ParameterError naming the others otherwise."""
    try:
        return _REGISTRY[name]
    except (KeyError, TypeError):
        raise ParameterError(f"method: expected one of {', '.join(_REGISTRY)}, got {name!r}") from None


def eval_systems() -> tuple[EvalSystem, ...]:
    """Every evaluation system the registered methods contribute, in registry order."""
    return tuple(s for m in _REGISTRY.values() for s in m.systems)


def system_method(system: str) -> tuple[Method, EvalSystem]:
    """The method that contributes evaluation system ``system``, and the system."""
    for m in _REGISTRY.values():
        for s in m.systems:
            if s.name == system:
                return m, s
    raise ParameterError(f"system: expected one of {', '.join(s.name for s in eval_systems())}, got {system!r}")
