"""Answering questions over Zenoh: a queryable at ``<namespace>/<key>`` whose requests are sigmaslam messages.

A :class:`QueryServer` takes queries from Zenoh's FIFO channel on a thread of its own (never on Zenoh's callback
threads, which also deliver the process's subscriptions), decodes each payload as the declared request type, calls
the handler and replies with the encoded answer. A payload that does not decode, and a request the handler refuses
(ValueError), get an error reply (``query.reply_err``) with the reason as UTF-8 text, counted and logged at most
once per period; any other exception of the handler is answered the same way, so the serving process never dies of
a question. :mod:`services.app.occupancy_client` is the asking side of ``map/query``.
"""

from __future__ import annotations

import logging
import threading
from typing import Callable

import zenoh

from shared import codec
from shared.codec import Message
from shared.ratelimit import RateLimitedLog

log = logging.getLogger(__name__)


class QueryServer:
    """One queryable and its answering thread; :meth:`close` undeclares it and ends the thread."""

    def __init__(self, session: zenoh.Session, key_expr: str, request: type[Message],
                 handler: Callable[[Message], Message], name: str = "") -> None:
        self.key_expr, self.request, self.handler, self.name = key_expr, request, handler, name or key_expr
        self.answered = self.refused = self.failed = 0
        self._log = RateLimitedLog(log)
        self._closing = threading.Event()
        self._queryable = session.declare_queryable(key_expr)
        self._thread = threading.Thread(target=self._serve, name=f"query-{self.name}", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while not self._closing.is_set():
            try:
                query = self._queryable.recv()
            except Exception:  # the queryable was undeclared (closing) or the session went away
                return
            try:
                self._answer(query)
            finally:
                query.drop()

    def _answer(self, query) -> None:
        try:
            payload = query.payload
            if payload is None:
                raise ValueError(f"a {self.request.__name__} payload is required")
            msg = codec.decode(payload.to_bytes(), expect=self.request)
            answer = self.handler(msg)
        except ValueError as exc:  # DecodeError is a ValueError too
            self.refused += 1
            self._log.warning("%s: query refused: %s", self.name, exc)
            self._reply_err(query, str(exc))
            return
        except Exception as exc:  # a bug of the handler: answered, logged, the process goes on
            self.failed += 1
            log.exception("%s: query failed", self.name)
            self._reply_err(query, f"internal error: {type(exc).__name__}: {exc}")
            return
        query.reply(query.key_expr, codec.encode(answer))
        self.answered += 1

    @staticmethod
    def _reply_err(query, text: str) -> None:
        try:
            query.reply_err(text.encode())
        except Exception as exc:  # the asker is gone
            log.debug("error reply not sent: %s", exc)

    def close(self) -> None:
        self._closing.set()
        try:
            self._queryable.undeclare()
        except Exception as exc:
            log.debug("%s: undeclare: %s", self.name, exc)
        self._thread.join(timeout=2.0)
