"""The contract of a synthesis method: what the CLI, the evaluation and the live server rely on.

A method is one module that defines a synthesizer class and a :class:`Method`
entry describing it; :mod:`gesturedb.synth.methods` registers the entry, and
every caller lists and opens methods through that registry (``gesturedb synth
--method``, ``gesturedb eval motion --systems``, the server) instead of naming them.

A synthesizer (:class:`Synthesizer`) is opened over a database once and then
synthesizes any number of utterances::

    method = gesturedb.synth.methods.get("knn")
    synth = method.open(db)                        # Searcher(db)
    result = synth.synthesize("speech.wav", options=method.options(seed=3))

``synthesize`` takes its method's options object (a :class:`gesturedb.synth.options.SynthOptions`
subclass, :attr:`Method.options`), or any of its fields as keywords, and returns a
:class:`gesturedb.synth.result.SynthResult` whose ``steps`` carry the provenance
(``out_start``/``out_end``, ``recording``, ``source_start_s``/``source_end_s``,
``control``, ``keyword`` for every method; the rest is the method's own).
A method that streams (:attr:`Method.streams`) also has ``stream(options=None, *,
sample_rate)`` returning an object with ``push(samples)``, ``push_words(words)``,
``set_control(expr)`` and ``finish()`` (issue 39; the offline result is the stream
fed the whole file).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Protocol, runtime_checkable

from gesturedb.synth.options import SynthOptions
from gesturedb.synth.result import SynthResult

__all__ = ["Synthesizer", "StreamingSynthesizer", "EvalSystem", "Method"]


@runtime_checkable
class Synthesizer(Protocol):
    """A synthesis method opened over one database."""

    db: Any

    def synthesize(self, audio, *, sr: int | None = None, transcript=None, options: SynthOptions | None = None,
                   **changes) -> SynthResult:
        """Gestures for speech: ``audio`` a WAV path or mono samples at ``sr``; ``transcript`` a path,
        :class:`gesturedb.io.transcripts.Words` or None; ``changes``: fields of the method's options."""
        ...


@runtime_checkable
class StreamingSynthesizer(Synthesizer, Protocol):
    """A synthesizer whose output can be pulled while the speech is still coming."""

    def stream(self, options: SynthOptions | None = None, *, sample_rate: int):
        ...


@dataclass(frozen=True)
class EvalSystem:
    """A system of ``gesturedb eval motion`` that a method contributes.

    Attributes
    ----------
    name : str
        Its key in the metrics (``ranksum_pose``).
    label : str
        Its name in tables and plots.
    color : str
        Its colour in every plot (matplotlib colour).
    options : dict
        Option fields that differ from the evaluation's shared options (``{"preselect": "audio"}``).
    """

    name: str
    label: str
    color: str
    options: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Method:
    """One synthesis method, as the registry holds it.

    Attributes
    ----------
    name : str
        Its name on the command line (``--method``) and in the provenance.
    summary : str
        One line for ``--help``.
    options : type
        Its options class (a :class:`SynthOptions` subclass with named defaults).
    open : callable ``(db, **settings) -> Synthesizer``
        Opens the method over a database; ``settings`` are the names in :attr:`settings`.
    settings : tuple of str
        Keywords of ``open`` beyond the database (how the k-NN reads the database:
        ``segments``, ``client``, ``parts``).
    streams : bool
        Its synthesizer has ``stream(...)`` (:class:`StreamingSynthesizer`).
    refines : bool
        Its ``synthesize`` takes ``refiner=`` (a trained refiner applied to the result).
    systems : tuple of EvalSystem
        What it adds to the objective evaluation.
    """

    name: str
    summary: str
    options: type
    open: Callable[..., Synthesizer]
    settings: tuple = ()
    streams: bool = False
    refines: bool = False
    systems: tuple = ()
