"""The lifecycle of sep's nodes: `Managed` (what `sep_plant.ros.base.NodeBase` does on each
transition of the ROS 2 node lifecycle), `managed_node` (the rclpy LifecycleNode whose
transitions call it), `autostart` (configure and activate at once), and the exceptions that end
a node: `StartError` (a refusal, exit code 2), `StopError`, `Shutdown`.

The standard lifecycle services (``<node>/change_state``, ``get_state``, ``get_available_states``,
``get_available_transitions``, ``get_transition_graph``) and the ``<node>/transition_event``
topic come from `rclpy.lifecycle` (docs/reference/topics.md). ROS-side module (imports rclpy).
"""
from __future__ import annotations

from typing import Any, Callable


class StartError(Exception):
    """A node cannot start (bad parameter, bad file, mismatch): logged, exit code 2."""

    exit_code = 2
    #: how the node's log line about it starts (`sep_plant.ros.process.run_node`)
    lead = 'refusing to start'


class StopError(StartError):
    """A check that passed at start fails after the node has run steps (the plant's scenario changed
    mid-episode): the node says that it stops and why, writes its summary with status 'error' and
    exits 2."""

    lead = 'stopping'


class Shutdown(Exception):
    """The node was shut down through its lifecycle (the shutdown transition): the process ends
    with its summary (status 'shutdown') and exit code 0."""


def autostart(node: Any, error: Callable[[], Exception | None], starting: Callable[[bool], None]) -> None:
    """Trigger the configure and activate transitions of the LifecycleNode `node` now (the
    parameter ``autostart``); raise `error()` when the configure was refused. `starting(flag)`
    tells the owner that the transitions are automatic (it then logs no line per transition:
    the start-up log stays what it was before the nodes were managed)."""
    starting(True)
    try:
        node.trigger_configure()
        exc = error()
        if exc is not None:
            raise exc
        node.trigger_activate()
    finally:
        starting(False)


class Managed:
    """The lifecycle side of a node (mixed into `sep_plant.ros.base.NodeBase`, which owns the
    rclpy node as ``self.node`` and its logger as ``self.log``).

    Subclasses put what loads and checks their files and creates their topics in
    ``configure()`` (raising StartError to refuse: the transition fails and the node logs why),
    and react to ``on_activated()`` / ``on_deactivated()``; ``active`` says whether the node acts.
    What ``configure()`` created (publishers, subscriptions, timers) is destroyed on cleanup,
    after the summary of an episode that ran steps (status 'cleaned_up'). ``shut_down`` is set by
    the shutdown transition (the process then ends).
    """

    def __init__(self) -> None:
        self.configured = self.active = self.shut_down = False
        self.prepared = False
        self.config_error: StartError | None = None
        self._starting = False
        self._entities: list = []

    def configure(self) -> None:
        """Load and check what the node needs, create its topics; StartError refuses."""

    def on_activated(self) -> None:
        """After the activate transition (default: nothing)."""

    def on_deactivated(self) -> None:
        """After the deactivate transition (default: nothing)."""

    def needs_configure(self) -> bool:
        """Whether this node has anything to configure (a node without ``configure()`` is ready
        as it is built: its health and summary need no transition)."""
        return type(self).configure is not Managed.configure

    def ready(self) -> bool:
        return self.configured or not self.needs_configure()

    def start(self) -> None:
        """autostart: the configure and activate transitions now; a refused configure raises its
        StartError (as the node's construction did before it was a managed node)."""
        autostart(self.node, lambda: self.config_error, self._set_starting)

    def _set_starting(self, flag: bool) -> None:
        self._starting = flag

    def state_label(self) -> str:
        """The lifecycle state ('unconfigured', 'inactive', 'active', 'finalized'); rclpy has no
        public accessor, get_state's service callback reads the same state machine."""
        return self.node._state_machine.current_state[1]

    def _entity_set(self) -> list:
        n = self.node
        return [*n.publishers, *n.subscriptions, *n.timers]

    def _do_configure(self) -> bool:
        """The configure transition: ``configure()``; on a refusal what it created is destroyed,
        ``config_error`` says why (logged unless autostarting: run_node logs it then)."""
        before = {id(e) for e in self._entity_set()}
        try:
            self.configure()
        except Exception as exc:  # noqa: BLE001 - a refused configure leaves the node unconfigured
            self._destroy([e for e in self._entity_set() if id(e) not in before])
            self.config_error = exc if isinstance(exc, StartError) else StartError(f'{type(exc).__name__}: {exc}')
            if not self._starting:
                self.log.error(f'configure failed, staying unconfigured: {self.config_error}')
            return False
        self._entities = [e for e in self._entity_set() if id(e) not in before]
        self.config_error, self.configured = None, True
        if not self._starting:
            self.log.info('configured')
        return True

    def _do_cleanup(self) -> None:
        """The cleanup transition: the summary of an episode that ran steps, then what
        ``configure()`` created destroyed; the node is unconfigured (configure may run again)."""
        if self.last_k >= 0 and not self.finished:
            self.finish('cleaned_up')
        self._destroy(self._entities)
        self._entities = []
        self.configured = self.prepared = self.done = self.finished = False
        self.last_k = -1
        self.log.info('cleaned up: unconfigured')

    def _destroy(self, entities) -> None:
        n = self.node
        for e in entities:
            for destroy in (n.destroy_publisher, n.destroy_subscription, n.destroy_timer):
                try:
                    if destroy(e):
                        break
                except Exception:  # noqa: BLE001 - not this kind of entity
                    continue

    def _set_active(self, active: bool) -> None:
        self.active = active
        (self.on_activated if active else self.on_deactivated)()
        if not self._starting:
            self.log.info('activated' if active else 'deactivated')


def managed_node(owner: Managed, node_name: str, namespace: str):
    """An rclpy LifecycleNode (namespace sep) whose transitions call `owner`: configure ->
    ``owner.configure()`` (a StartError fails the transition), activate / deactivate ->
    ``owner.active``, cleanup -> the configured entities destroyed, shutdown -> ``owner.shut_down``
    (the process then ends)."""
    from rclpy.lifecycle import LifecycleNode, TransitionCallbackReturn

    ok, failed = TransitionCallbackReturn.SUCCESS, TransitionCallbackReturn.FAILURE

    class _Managed(LifecycleNode):
        def on_configure(self, state):
            return ok if owner._do_configure() else failed

        def on_activate(self, state):
            owner._set_active(True)
            return ok

        def on_deactivate(self, state):
            owner._set_active(False)
            return ok

        def on_cleanup(self, state):
            owner._do_cleanup()
            return ok

        def on_shutdown(self, state):
            if owner.active:
                owner._set_active(False)
            owner.shut_down = True
            owner.log.info('shut down')
            return ok

        def on_error(self, state):
            owner.active = False
            return ok

    return _Managed(node_name, namespace=namespace)
