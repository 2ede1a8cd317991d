"""Services that answer every caller without holding an executor thread while their work goes on.

rclpy runs a service callback on the executor and sends what it returns. A callback that waits for a long job
(saving a map takes seconds) would hold an executor thread all that time, and twenty callers would hold twenty
threads or queue behind each other, while the node must go on mapping. Here the callback only starts the job
(or joins one, see :class:`~lego_loam_py.formats.CoalescingRunner`) and returns at once; the response is sent
when the job's future completes, from the thread that completes it.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

__all__ = ['create_deferred_service', 'SERVICE_QUEUE_DEPTH']

# Requests a service keeps while they wait to be taken: as many callers as any robot's tools will have at once
# (rclpy's default of 10 silently drops the eleventh caller of a busy service).
SERVICE_QUEUE_DEPTH = 100
RESPONSE_RETRY_S = 10.0  # how long a response is retried while the caller's response reader is discovered
RESPONSE_SPACING_S = 0.01  # between two answers of the same run (see done() below)


def _send(send_now, response, header) -> bool:
    try:
        send_now(response, header)
        return True
    except Exception:  # rclpy raises when the rmw times out on the caller (or the node is shutting down)
        return False


def _send_until_matched(send_now, response, header) -> None:
    deadline = time.monotonic() + RESPONSE_RETRY_S
    while time.monotonic() < deadline:
        time.sleep(0.05)
        if _send(send_now, response, header):
            return


def create_deferred_service(
    node, srv_type, name: str, start: Callable[[Any], Future], fill: Callable[[Any, Future], None], callback_group=None
):
    """A service ``name`` of ``srv_type`` on ``node``: ``start(request)`` returns a Future of the work, and
    ``fill(response, future)`` writes the finished work into the response, which is then sent."""
    waiting: dict[int, Future] = {}
    lock = threading.Lock()

    def callback(request, response):
        future = start(request)
        with lock:
            waiting[id(response)] = future
        return response

    qos = QoSProfile(
        depth=SERVICE_QUEUE_DEPTH,
        history=HistoryPolicy.KEEP_LAST,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
    )
    service = node.create_service(srv_type, name, callback, qos_profile=qos, callback_group=callback_group)
    send_now = service.send_response

    def send_response(response, header) -> None:
        with lock:
            future = waiting.pop(id(response), None)
        if future is None:
            send_now(response, header)
            return

        def done(finished: Future) -> None:
            fill(response, finished)
            if not _send(send_now, response, header):
                # A caller that asked right after creating its client: the rmw gives up on it (100 ms) while its
                # response reader is still being discovered. Keep trying for a while, off this thread.
                threading.Thread(target=_send_until_matched, args=(send_now, response, header), daemon=True).start()
            # Every client of a service receives every response and keeps rclpy's default of 10: the answers of
            # one coalesced run, sent back to back to twenty callers, would push a caller's own answer out of its
            # queue before it is taken. A few milliseconds apart, each client takes them as they come.
            time.sleep(RESPONSE_SPACING_S)

        future.add_done_callback(done)

    service.send_response = send_response  # rclpy's executor sends what the callback returned through this
    return service
