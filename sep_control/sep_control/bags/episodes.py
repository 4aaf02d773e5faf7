"""Bags of several episodes (pure: no rclpy): `split_episodes`, `read_episodes`, `analyze_episodes`.

A plant with the parameter ``episodes`` != 1 plays episode after episode in one process; the
recorder writes them all into one bag (docs/reference/topics.md). Each episode begins with the
plant's scenario message carrying ``"episode": {"index": i, "of": K, "seed": s, "run": r}``
(`sep_plant.scenario.episode_entry`), published after every message of the episode before it was
acknowledged by its readers; so in the bag's receive-time order an episode is the scenario
message that announces it and every message after it, up to the next announcement. Messages
before the first announcement belong to the first episode.

A bag without episode entries is one episode (index None): `read_episodes` then returns it alone.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from sep_control.bags.messages import cdr_string, open_bag
from sep_control.bags.reader import Episode, episode_of_raw
from sep_control.bags.storage import RawBag
from sep_plant import topics as T
from sep_plant.scenario import ScenarioError, scenario_message_parts


@dataclass
class RecordedEpisode:
    """One episode of a bag: its index, seed and run (None for a single-episode bag) and its arrays."""

    index: int | None
    seed: int | None
    run: int | None
    episode: Episode


def announcements(raw: RawBag, namespace: str) -> list[tuple[int, dict[str, int]]]:
    """(message position in receive-time order, episode entry) of every scenario message that
    announces an episode other than the one before it."""
    order = np.argsort(raw.log_times, kind='stable')
    scen_ids = {cid for cid, c in raw.connections.items() if T.key_of(c.topic, namespace) == T.SCENARIO}
    out: list[tuple[int, dict[str, int]]] = []
    for pos, i in enumerate(order.tolist()):
        if int(raw.conn_ids[i]) not in scen_ids:
            continue
        try:
            entry = scenario_message_parts(cdr_string(raw.data[i]))[3]
        except (ScenarioError, ValueError, IndexError, UnicodeDecodeError, struct.error):
            continue
        if entry is not None and (not out or out[-1][1]['index'] != entry['index']):
            out.append((pos, entry))
    return out


def split_episodes(raw: RawBag, namespace: str) -> list[tuple[dict[str, int] | None, RawBag]]:
    """The bag cut at its episode announcements: (entry, that episode's messages as a RawBag in
    receive-time order); one part with entry None when the bag announces no episode."""
    marks = announcements(raw, namespace)
    if not marks:
        return [(None, raw)]
    order = np.argsort(raw.log_times, kind='stable')
    bounds = [0] + [pos for pos, _ in marks[1:]] + [len(order)]
    parts = []
    for (_, entry), lo, hi in zip(marks, bounds[:-1], bounds[1:]):
        idx = order[lo:hi]
        parts.append((entry, replace(raw, conn_ids=raw.conn_ids[idx], log_times=raw.log_times[idx],
                                     data=[raw.data[i] for i in idx.tolist()], notes=list(raw.notes))))
    return parts


def read_episodes(path: str | Path, scenario=None, info=None, *, namespace: str | None = None,
                  allow_truncated: bool = False) -> list[RecordedEpisode]:
    """Every episode of a bag as arrays (`sep_control.bags.reader.read_episode` of each part).

    Parameters are those of `read_episode`. Returns the episodes in the order recorded."""
    raw, name = open_bag(path, allow_truncated)
    if namespace is None:
        namespace = T.detect_namespace({c.topic for c in raw.connections.values()}) or T.NAMESPACE
    out = []
    for entry, part in split_episodes(raw, namespace):
        ep = episode_of_raw(part, name, Path(path), scenario, info, namespace)
        out.append(RecordedEpisode(*((entry['index'], entry['seed'], entry['run']) if entry else (None,) * 3), ep))
    return out


def episode_name(path: str | Path, index: int | None) -> str:
    """``BAG.e<i>`` (the bag's directory or file stem), or ``BAG`` for a single-episode bag."""
    p = Path(path)
    stem = p.stem if p.is_file() else p.name
    return stem if index is None else f'{stem}.e{index}'


def analyze_episodes(path: str | Path, design=None, *, allow_mismatch: bool = False, allow_truncated: bool = False,
                     namespace: str | None = None) -> Any:
    """Metrics of each episode of a multi-episode bag (rows BAG.e0, BAG.e1, ...) and pooled
    (`sep_control.bags.analysis.aggregate`): an AggregateReport; a bag of one episode gives its
    EpisodeReport (`analyze`)."""
    from sep_control.bags.analysis import _load_design, aggregate, analyze_episode

    design = _load_design(design)
    eps = read_episodes(path, scenario=design.scenario if design is not None else None,
                        info=design.info if design is not None else None, namespace=namespace,
                        allow_truncated=allow_truncated)
    reports = [analyze_episode(e.episode, design, allow_mismatch=allow_mismatch, name=episode_name(path, e.index))
               for e in eps]
    if len(reports) == 1 and eps[0].index is None:
        return reports[0]
    return aggregate(reports, design)


__all__ = ['RecordedEpisode', 'analyze_episodes', 'announcements', 'episode_name', 'read_episodes', 'split_episodes']
