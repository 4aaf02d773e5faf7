"""When a controller node (estimator, lqr, lqg) moves on to the plant's next episode.

A plant with the parameter ``episodes`` != 1 plays episode after episode in one process and
announces each one with a new scenario message carrying ``"episode": {"index": i, ...}``
(`sep_plant.scenario.episode_entry`), after episode i-1 ended (completed, or cut off when a
lockstep command did not come). A controller resets its filter and controller for episode i:

* at once, when it is between episodes: it has handled no step of its episode yet, or its last
  step N;
* else later (the announcement is pending): when it has handled step N of the old episode (the
  announcement overtook the old episode's last measurement), or when a message stamped at or
  before the last step it handled arrives (the old episode was cut off: the plant began anew).

The first announcement a node sees only tells it which episode it joins (it starts fresh).
Pure Python: no ROS import.
"""
from __future__ import annotations


class EpisodeSwitch:
    """The episode a controller node serves (`index`; None: a single-episode plant, or none
    announced yet) and the one announced next (`pending`)."""

    def __init__(self) -> None:
        self.index: int | None = None
        self.of: int | None = None           # episodes the plant plays (0: until stopped)
        self.pending: int | None = None

    @property
    def multi(self) -> bool:
        """Whether the plant announced episodes (it plays more than one)."""
        return self.of is not None

    def last_episode(self) -> bool:
        """Whether the episode served is the plant's last (never for a plant that plays until stopped)."""
        return not self.multi or (self.of > 0 and self.index is not None and self.index >= self.of - 1)

    def announce(self, index: int, of: int, busy: bool) -> bool:
        """The plant announced episode `index` (of `of`); `busy`: the node has handled steps of its
        episode but not its last. True: reset for it now."""
        self.of = of
        if self.index is None:
            self.index = index
            return False
        if index == self.index:
            return False                      # the same announcement again (a late joiner's latched copy)
        if busy:
            self.pending = index
            return False
        self.index, self.pending = index, None
        return True

    def take_pending(self) -> bool:
        """The old episode is over (its step N handled, or a message from before its last step
        came): True, and the pending episode is the one served, when one was announced."""
        if self.pending is None:
            return False
        self.index, self.pending = self.pending, None
        return True
