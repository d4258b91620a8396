"""The paper's dictionaries (design §6, paper Table 1), each a small object composed with EDMD.

A :class:`Dictionary` knows three things about its lifted vector: how to *lift* a settled
sensing into a sample (``lift``), how to turn a predicted sample back into an *offset* to move
by (``offset``), and how to *bridge* a lost or missed tick with the model's own prediction
(``lift`` with ``predicted``, ``skip``). :class:`EDMDPolicy` composes one dictionary with a
:class:`agents.estimators.StreamingEDMD`; it has no per-letter branches.
"""
from __future__ import annotations

import numpy as np

from agents.estimators import NotFitted, StreamingEDMD
from agents.policies.base import Policy, Proposal, Unwrapper, polar, relative
from protocol.messages import Sensing

Sample = tuple[np.ndarray | None, tuple[float, ...]]  # (sample to observe, measurement recorded)


class Dictionary:
    """Lifted vector of one dictionary; subclasses override what differs."""

    name = "dictionary"
    bridges_missed = False  # a missed tick is bridged by appending the model's prediction

    def query(self) -> np.ndarray | None:
        """The sample to predict from, if not the last observed one (raises NotFitted)."""
        return None

    def offset(self, pre: Sensing, z: np.ndarray) -> np.ndarray:
        """Local-frame offset (2,) to the estimate, from the predicted sample ``z``."""
        raise NotImplementedError

    def lift(self, settled: Sensing, predicted: np.ndarray | None) -> Sample:
        """The sample to observe for this tick; ``predicted`` is given when the rod was lost."""
        raise NotImplementedError

    def bridge(self, z: np.ndarray) -> np.ndarray:
        """The sample that stands in for a missed tick's measurement (``bridges_missed``)."""
        return z


class Velocity(Dictionary):
    """a: the follower's velocity ``v``; estimate ``f_j + T_c v*``."""

    name = "a"

    def __init__(self, comm_period: float) -> None:
        self.comm_period = comm_period

    def offset(self, pre: Sensing, z: np.ndarray) -> np.ndarray:
        return self.comm_period * z

    def lift(self, settled: Sensing, predicted: np.ndarray | None) -> Sample:
        if settled.velocity is None:
            return None, ()
        v = np.asarray(settled.velocity, dtype=float)
        return v, tuple(v)


def polar_offset(pre: Sensing, z: np.ndarray) -> np.ndarray:
    """Offset to the estimate ``l_{j+1} - r* (cos, sin) theta*`` of a predicted ``z = (r*,
    theta*, ...)``, with the leader as sensed before moving."""
    return relative(pre) - polar(z[0], z[1])


def settled_polar(unwrap: Unwrapper, settled: Sensing,
                  predicted: np.ndarray | None) -> tuple[float, float]:
    """The ``(r, theta)`` to record: the settled reading, or the prediction on a lost tick
    (multi-step), with theta unwrapped."""
    theta = settled.theta if predicted is None else float(predicted[1])
    r = settled.r if predicted is None else float(predicted[0])
    return (r, unwrap(theta))


class RelativePolar(Dictionary):
    """b: the relative position ``(r, theta)``; estimate ``l_{j+1} - r* (cos, sin) theta*``."""

    name = "b"
    bridges_missed = True

    def __init__(self) -> None:
        self.unwrap = Unwrapper()

    def offset(self, pre: Sensing, z: np.ndarray) -> np.ndarray:
        return polar_offset(pre, z)

    def lift(self, settled: Sensing, predicted: np.ndarray | None) -> Sample:
        rel = settled_polar(self.unwrap, settled, predicted)
        return np.asarray(rel), rel

    def bridge(self, z: np.ndarray) -> np.ndarray:
        self.unwrap(float(z[1]))
        return z


class RelativeCartesian(Dictionary):
    """b-xy: the relative position as xy (beyond the paper: no bearing wrap-around)."""

    name = "b-xy"
    bridges_missed = True

    def offset(self, pre: Sensing, z: np.ndarray) -> np.ndarray:
        return relative(pre) - z

    def lift(self, settled: Sensing, predicted: np.ndarray | None) -> Sample:
        x = relative(settled) if predicted is None else np.asarray(predicted, dtype=float)
        return x, tuple(x)


class Absolute(Dictionary):
    """d–g: absolute positions (GPS); estimate the first two predicted components."""

    bridges_missed = True
    PARTS = {"d": (2, 0), "e": (3, 0), "f": (2, 2), "g": (3, 3)}  # own, leader components

    def __init__(self, letter: str) -> None:
        self.name = letter
        self.own, self.lead = self.PARTS[letter]

    def offset(self, pre: Sensing, z: np.ndarray) -> np.ndarray:
        return z[:2] - np.asarray(pre.gps[:2])

    def lift(self, settled: Sensing, predicted: np.ndarray | None) -> Sample:
        if settled.gps is None or settled.leader_gps is None:
            raise RuntimeError(f"dictionary {self.name!r} needs GPS: run with gps enabled")
        z = np.r_[settled.gps[: self.own], settled.leader_gps[: self.lead]]
        return z, tuple(z)


class RelativeVelocity(Dictionary):
    """c: ``(r, theta, v)``. The current velocity is not known yet when predicting (paper
    §4.3); ``variant`` says what stands in: ``oracle`` (the world's exact one), ``lagged``
    (the last measured) or ``estimated`` (a separate EDMD on the velocity history). For
    lagged/estimated, a sample is appended once its velocity is measured (one tick later)."""

    def __init__(self, variant: str, **estimator) -> None:
        if variant not in ("oracle", "lagged", "estimated"):
            raise ValueError(f"velocity must be oracle, lagged or estimated, got {variant!r}")
        self.variant = variant
        self.name = f"c-{variant}"
        self.unwrap = Unwrapper()
        self.velocity_edmd = StreamingEDMD(**estimator) if variant == "estimated" else None
        self.last_rel: tuple[float, float] | None = None
        self.last_velocity: np.ndarray | None = None
        self.pending: tuple[float, float] | None = None

    def _current_velocity(self) -> np.ndarray:
        if self.velocity_edmd is not None and self.velocity_edmd.n_pairs >= 1:
            return self.velocity_edmd.predict()
        if self.last_velocity is None:
            raise NotFitted("dictionary c needs a measured velocity")
        return self.last_velocity

    def query(self) -> np.ndarray | None:
        if self.variant == "oracle":
            return None
        if self.last_rel is None:
            raise NotFitted("dictionary c needs a relative position")
        return np.r_[self.last_rel, self._current_velocity()]

    def offset(self, pre: Sensing, z: np.ndarray) -> np.ndarray:
        return polar_offset(pre, z)

    def lift(self, settled: Sensing, predicted: np.ndarray | None) -> Sample:
        rel = settled_polar(self.unwrap, settled, predicted)
        velocity = None if settled.velocity is None else np.asarray(settled.velocity, dtype=float)
        sample = None
        if self.variant == "oracle":
            if settled.oracle_velocity is None:
                raise RuntimeError("velocity 'oracle' needs the world's oracle velocity")
            sample = np.r_[rel, settled.oracle_velocity]
            measurement = tuple(sample)
        else:  # the previous sample's velocity is known now: complete it
            if self.pending is not None and velocity is not None:
                sample = np.r_[self.pending, velocity]
            self.pending = rel
            measurement = rel + (tuple(velocity) if velocity is not None else ())
        self.last_rel = rel
        if velocity is not None:
            self.last_velocity = velocity
            if self.velocity_edmd is not None:
                self.velocity_edmd.observe(velocity)
        return sample, measurement

    def drop_pending(self) -> None:
        self.pending = None


def make_dictionary(letter: str, comm_period: float, velocity: str = "lagged",
                    cartesian: bool = False, **estimator) -> Dictionary:
    """The dictionary object for a letter of design §6's table."""
    if not isinstance(letter, str) or len(letter) != 1 or letter not in "abcdefg":
        raise ValueError(f"dictionary must be one of a..g, got {letter!r}")
    if cartesian and letter != "b":
        raise ValueError("cartesian applies to dictionary b only")
    if letter == "a":
        return Velocity(comm_period)
    if letter == "b":
        return RelativeCartesian() if cartesian else RelativePolar()
    if letter == "c":
        return RelativeVelocity(velocity, **estimator)
    return Absolute(letter)


def edmd_name(dictionary: Dictionary, delays: int = 0, affine: bool = False,
              window: int | None = None, **_) -> str:
    """A readable, unique name: ``edmd-b``, ``edmd-b-xy-d2``, ``edmd-a-d1-aff-w8``..."""
    name = f"edmd-{dictionary.name}"
    name += f"-d{delays}" if delays else ""
    name += "-aff" if affine else ""
    name += f"-w{window}" if window else ""
    return name


class EDMDPolicy(Policy):
    """Data-streaming EDMD (paper Algorithm 1) on one dictionary.

    Parameters
    ----------
    dictionary : Dictionary
        What is lifted and how a prediction becomes a move.
    name : str, optional
        Defaults to ``edmd-<dictionary>`` plus the non-default estimator options.
    determined : bool, default False
        Propose only a prediction the data determine beyond the readings' noise: one whose
        leverage (:meth:`StreamingEDMD.noise_gain`) is at most 1, so the fit carries less of
        the noise into it than the newest reading holds. Otherwise :class:`NotFitted` is
        raised, and :class:`agents.policies.base.FallbackToPersist` has ``persist`` (the
        newest reading reused) stand in, counted as a fallback tick. Without noise leverage
        costs nothing, so it is off (the paper's Algorithm 1 as published); a driving
        follower with declared noise turns it on (:func:`agents.policies.make_policy`,
        design §4).
    **estimator
        Keyword arguments of :class:`StreamingEDMD` (online, delays, affine, forget, window,
        ridge).
    """

    def __init__(self, dictionary: Dictionary, name: str | None = None,
                 determined: bool = False, **estimator) -> None:
        self.dictionary = dictionary
        self.edmd = StreamingEDMD(**estimator)
        self.name = name or edmd_name(dictionary, **estimator)
        self.determined = determined

    def _predict(self) -> np.ndarray:
        return self._predict_from(self.dictionary.query())

    def _predict_from(self, query: np.ndarray | None) -> np.ndarray:
        """The prediction from the dictionary's ``query`` (None: the newest sample)."""
        return self.edmd.predict() if query is None else self.edmd.predict(query)

    def _predict_or_none(self) -> np.ndarray | None:
        try:
            return self._predict()
        except NotFitted:
            return None

    def propose(self, pre: Sensing) -> Proposal:
        query = self.dictionary.query()
        if self.determined and (gain := self.edmd.noise_gain(query)) > 1:
            raise NotFitted(f"leverage {gain:.3g} > 1: the pairs do not determine the "
                            "prediction beyond the readings' noise")
        z = self._predict_from(query)
        return Proposal(self.dictionary.offset(pre, z), tuple(float(x) for x in z))

    def record(self, settled: Sensing, target: np.ndarray | None) -> tuple[float, ...]:
        """Append the settled measurement; when the rod was lost (``target`` None) the
        dictionary may append the model's own prediction instead (multi-step)."""
        predicted = self._predict_or_none() if target is None else None
        sample, measurement = self.dictionary.lift(settled, predicted)
        if sample is not None:
            self.edmd.observe(sample)
        return tuple(float(x) for x in measurement)

    def skip(self) -> None:
        """Bridge a missed tick with the model's own prediction where the lifted vector is a
        state of the formation; drop half-built dictionary-c samples."""
        if isinstance(self.dictionary, RelativeVelocity):
            self.dictionary.drop_pending()
        if self.dictionary.bridges_missed and self.edmd.n_pairs >= 1:
            self.edmd.observe(self.dictionary.bridge(self.edmd.predict()))


def paper_edmd(letter: str, comm_period: float, velocity: str = "lagged",
               determined: bool = False, **estimator) -> EDMDPolicy:
    """EDMD on dictionary ``letter`` named as before the split (``edmd-b``, ``edmd-c-lagged``);
    ``determined`` as :class:`EDMDPolicy`'s."""
    dictionary = make_dictionary(letter, comm_period, velocity, **estimator)
    return EDMDPolicy(dictionary, name=f"edmd-{dictionary.name}", determined=determined,
                      **estimator)
