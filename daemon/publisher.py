"""The daemon's Zenoh face: the keys of interfaces.md under ``cubeloc/<name>/``.

========================  ============  ==============================================
``pose``                  publication   ``cubeloc.pose/3``, every frame with a pose
``base_pose``             publication   ``cubeloc.pose/4`` (map -> base_link), with ``[frames]``
``map_odom``              publication   ``cubeloc.map_odom/1`` (map -> odom, REP 105), with ``[odometry]``
``status``                publication   ``cubeloc.status/1``, once a second
``alive``                 liveliness    present while the daemon runs
``calibration``           queryable     the camera_info YAML in use
``reset``                 queryable     re-initialise on the target (deny it with Zenoh ACL)
========================  ============  ==============================================

``pose``, ``base_pose`` and ``map_odom`` use congestion control DROP and express with a high priority: a slow or absent
subscriber costs a message, never a stalled loop.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import TYPE_CHECKING

import structlog

if TYPE_CHECKING:  # pragma: no cover
    import zenoh

log = structlog.get_logger()


def key_prefix(name: str) -> str:
    return f"cubeloc/{name}"


class ZenohPublisher:
    """Declares everything at construction; ``close`` undeclares it (before the session closes)."""

    def __init__(
        self,
        session: zenoh.Session,
        name: str,
        calibration_yaml: str,
        request_reset: Callable[[], bool],
        base_pose: bool = False,
        map_odom: bool = False,
    ) -> None:
        import zenoh

        self._zenoh = zenoh
        prefix = key_prefix(name)
        self.prefix = prefix
        self.calibration_yaml = calibration_yaml  # replaced whole on a reload (SIGHUP)
        self._request_reset = request_reset
        self._session = session
        self._pose = self._pose_publisher(f"{prefix}/pose")
        self._base_pose = self._pose_publisher(f"{prefix}/base_pose") if base_pose else None
        self._map_odom = self._pose_publisher(f"{prefix}/map_odom") if map_odom else None
        self._status = session.declare_publisher(
            f"{prefix}/status",
            encoding=zenoh.Encoding.APPLICATION_JSON,
            congestion_control=zenoh.CongestionControl.DROP,
            priority=zenoh.Priority.DATA,
        )
        self._alive = session.liveliness().declare_token(f"{prefix}/alive")
        self._calibration = session.declare_queryable(f"{prefix}/calibration", self._on_calibration)
        self._reset = session.declare_queryable(f"{prefix}/reset", self._on_reset)
        self._closed = False
        log.info("zenoh keys declared", prefix=prefix)

    def _pose_publisher(self, key: str):
        return self._session.declare_publisher(
            key,
            encoding=self._zenoh.Encoding.APPLICATION_JSON,
            congestion_control=self._zenoh.CongestionControl.DROP,
            priority=self._zenoh.Priority.INTERACTIVE_HIGH,
            express=True,
        )

    def publish_pose(self, payload: bytes) -> None:
        self._pose.put(payload)

    def publish_base_pose(self, payload: bytes) -> None:
        self._base_pose.put(payload)

    def publish_map_odom(self, payload: bytes) -> None:
        self._map_odom.put(payload)

    def publish_status(self, payload: bytes) -> None:
        self._status.put(payload)

    # Replies go out on the concrete key, whatever the selector (``cubeloc/*/calibration``),
    # so the caller learns which daemon answered. Payload, parameters and attachment of a
    # query are ignored: nothing a peer sends can change what these do.
    def _on_calibration(self, query: zenoh.Query) -> None:
        query.reply(f"{self.prefix}/calibration", self.calibration_yaml.encode("utf-8"),
                    encoding=self._zenoh.Encoding.TEXT_YAML)

    def _on_reset(self, query: zenoh.Query) -> None:
        key = f"{self.prefix}/reset"
        if str(query.key_expr) != key:
            # A wildcard selector (``cubeloc/**`` from a monitoring tool) reaches this
            # queryable too; resetting every daemon it matches would be a nasty surprise.
            query.reply(key, json.dumps({"reset": False, "reason": f"ask {key} exactly"}).encode("utf-8"),
                        encoding=self._zenoh.Encoding.APPLICATION_JSON)
            return
        # Runs on a Zenoh thread: the processing loop performs the reset (it owns the
        # processor); this waits briefly for it so the caller learns whether it happened.
        done = self._request_reset()
        log.info("reset requested over zenoh", done=done, **self._who_asked(query))
        query.reply(key, json.dumps({"reset": done}).encode("utf-8"),
                    encoding=self._zenoh.Encoding.APPLICATION_JSON)

    def _who_asked(self, query: zenoh.Query) -> dict[str, object]:
        """For the log: the name Zenoh authenticated on the link of the session the query
        says it comes from (its source info, which a querier sets, e.g.
        ``session.get(..., source_info=SourceInfo(querier.id, 1))``); without one, the
        authenticated names of every session connected now. Zenoh 1.10 names a link by
        its TLS certificate's common name (mutual TLS), not by a user/password login."""
        try:
            links = list(self._session.info.links())
        except self._zenoh.ZError:
            return {}
        names = {str(link.zid): link.auth_identifier for link in links if link.auth_identifier}
        source = query.source_info
        if source is not None and source.source_id is not None:
            zid = str(source.source_id.zid)
            return {"asked_by": names.get(zid, "unnamed (no certificate on its link)"), "asked_by_zid": zid}
        return {"asked_by": "unknown (no source info in the query)",
                "authenticated_sessions": sorted(set(names.values()))}

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for entity in (self._reset, self._calibration, self._alive, self._status, self._pose, self._base_pose):
            if entity is None:
                continue
            try:
                entity.undeclare()
            except self._zenoh.ZError as exc:  # the session may already be closing
                log.debug("undeclare failed", error=str(exc))
