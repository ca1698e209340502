"""The books kept on an interrogator's sample numbers: one counter, one meaning, for every driver, the live loop
and replay (:class:`SequenceCounter`, whose rule is :func:`lost_before`).

The rule, number by number:

- a step of one is the next sample;
- a forward jump of ``d`` is a gap of ``d − 1`` lost samples, up to :data:`MAX_LOST`; a longer jump (2**62 after
  10) is no outage an instrument can have — its counter was re-seeded or the number is corrupt — so it is a
  reset, not loss;
- a backward or repeated number is a reset (a restarted acquisition, a counter that wrapped), not loss;
- look-back: when the number after a jump or reset continues the run *before* it (forward, within
  :data:`MAX_LOST`) more closely than it continues the jump, the jump was one corrupt number — 10, 2**62, 12 is
  one corrupt record (``sequence_corrupt``), no loss and no reset: what the jump booked is taken back, the
  corrupt record stands for sample 11, and losses are counted from there. A jump followed by numbers
  continuing it stands (a genuine restart or gap);
- a negative number means "unknown" and is skipped (it neither counts nor moves the reference); a number
  beyond int64 (a u64 serial number of 2**63 or more: 29 million years at 10 kHz) is taken as 2**63 − 1, as
  absurd as it was, and judged by the rule like any other (:data:`INT64_MAX`).

Each decision depends only on the numbers so far, never on how they were batched, so a stream counted live and
the same frames replayed from a recording give the same figures; a jump is booked when it arrives and taken back
when the next number shows it corrupt (a frame's gap flag, set as it arrives, stays).
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["INT64_MAX", "MAX_LOST", "SequenceCounter", "clamp", "lost_before"]

INT64_MAX = 2**63 - 1

#: longest gap counted as lost samples: 2**32 samples, 5 days at 10 kHz (the fastest interrogator here samples
#: at 5 kHz); a longer forward jump is a reset (a re-seeded or corrupt counter)
MAX_LOST = 2**32

# the state of the books between batches, an int64 array: the reference, whether the books are open, and the
# last number's booking when it may yet be taken back (the run's reference before it, −1: none; 1 gap / 2 reset;
# the samples it booked lost)
_LAST, _OPEN, _CAND_REF, _CAND_KIND, _CAND_LOST = range(5)
_GAP, _RESET = 1, 2


def clamp(sequence: int) -> int:
    """A sample number as the books take it: one beyond int64 (a u64 counter's 2**63 or more) is 2**63 − 1 (the
    decoders of unsigned counters call this, so that a batch of frames holds int64 numbers)."""
    return min(int(sequence), INT64_MAX)


class SequenceCounter:
    """Counts sequence gaps, lost samples, resets and corrupt numbers of a stream of sample numbers (the rule:
    module docstring).

    Attributes
    ----------
    sequence_gaps, lost_samples, sequence_resets, sequence_corrupt : int
    state : ndarray of int64 (5,)
        The books between batches (what :func:`lost_before` takes and updates).
    """

    def __init__(self) -> None:
        self.state = np.array([-1, 0, -1, 0, 0], np.int64)
        self.sequence_gaps = 0
        self.lost_samples = 0
        self.sequence_resets = 0
        self.sequence_corrupt = 0

    @property
    def last(self) -> int | None:
        """The last (non-negative) sample number counted, None before any."""
        return int(self.state[_LAST]) if self.state[_OPEN] else None

    def count(self, sequence: int) -> int:
        """Count one sample number; return how many samples were lost just before it."""
        return int(self.count_many([sequence])[0])

    def count_many(self, sequences) -> np.ndarray:
        """Count a batch of sample numbers in order; return, per number, the samples lost just before it.

        Parameters
        ----------
        sequences : array_like of int, shape (n,)

        Returns
        -------
        ndarray of int64, shape (n,)
            0 for a number that follows its predecessor, for a reset and for an unknown (negative) number.
        """
        try:
            seq = np.asarray(sequences, dtype=np.int64).reshape(-1)
        except OverflowError:  # a number beyond int64: as absurd as it was (module docstring)
            seq = np.array([clamp(s) for s in np.asarray(sequences, dtype=object).ravel()], dtype=np.int64)
        lost, *books = lost_before(seq, self.state)
        self.book(*books)
        return lost

    def book(self, gaps: int, resets: int, corrupt: int, lost_hi: int, lost_lo: int) -> None:
        """Add what :func:`lost_before` found in a batch (for a caller that runs it inside its own compiled
        pass, as the live loop does; :meth:`count_many` otherwise). The deltas may be negative: a jump booked in
        an earlier batch taken back."""
        self.sequence_gaps += int(gaps)
        # each gap fits 33 bits but their sum may not fit int64: add the high and low 32 bits separately (exact,
        # and the same whatever batches the numbers came in)
        self.lost_samples += (int(lost_hi) << 32) + int(lost_lo)
        self.sequence_resets += int(resets)
        self.sequence_corrupt += int(corrupt)

    def as_dict(self) -> dict[str, int]:
        """The four counters, JSON-ready."""
        return {"sequence_gaps": self.sequence_gaps, "lost_samples": self.lost_samples,
                "sequence_resets": self.sequence_resets, "sequence_corrupt": self.sequence_corrupt}


@njit(cache=True, nogil=True)
def lost_before(seq, state):
    """Count a batch of sample numbers by the module's rule, updating ``state`` (a :class:`SequenceCounter`'s)
    in place.

    Returns
    -------
    lost : ndarray of int64 (n,)
        Samples lost just before each number, as decided when it arrived.
    gaps, resets, corrupt, lost_hi, lost_lo : int
        The batch's changes to the books (negative when it takes back a jump booked in an earlier batch); the
        losses as sums of their high and low 32 bits.

    One compiled pass: the numpy form cost ≈ 15 µs of array calls per batch, twice per batch in the live path.
    """
    lost = np.zeros(seq.size, np.int64)
    gaps = resets = corrupt = lost_hi = lost_lo = 0
    last, is_open = state[_LAST], state[_OPEN]
    cand_ref, cand_kind, cand_lost = state[_CAND_REF], state[_CAND_KIND], state[_CAND_LOST]
    for i in range(seq.size):
        s = seq[i]
        if s < 0:
            continue
        if not is_open:  # the first number ever seen opens the books
            is_open = 1
            last = s
            continue
        ref = last
        if cand_ref >= 0:
            # the last number jumped: does this one continue the run before the jump more closely than the jump?
            back, step = s - cand_ref, s - last
            if 0 < back <= MAX_LOST + 1 and not 0 < step <= back:
                corrupt += 1
                if cand_kind == _GAP:
                    gaps -= 1
                    lost_hi -= cand_lost >> 32
                    lost_lo -= cand_lost & 0xFFFFFFFF
                else:
                    resets -= 1
                # the corrupt record stood for the sample after the run (unless this one is that sample)
                ref = cand_ref + 1 if back > 1 else cand_ref
        d = s - ref
        cand_ref = -1
        if d != 1:
            cand_ref = ref
            if 1 < d <= MAX_LOST + 1:
                cand_kind = _GAP
                cand_lost = d - 1
                lost[i] = d - 1
                gaps += 1
                lost_hi += (d - 1) >> 32
                lost_lo += (d - 1) & 0xFFFFFFFF
            else:
                cand_kind = _RESET
                resets += 1
        last = s
    state[_LAST], state[_OPEN] = last, is_open
    state[_CAND_REF], state[_CAND_KIND], state[_CAND_LOST] = cand_ref, cand_kind, cand_lost
    return lost, gaps, resets, corrupt, lost_hi, lost_lo
