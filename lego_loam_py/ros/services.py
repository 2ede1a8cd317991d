"""Services that answer every caller without holding an executor thread while their work goes on.

rclpy runs a service callback on the executor and sends what it returns. A callback that waits for a long job
(saving a map takes seconds) would hold an executor thread all that time, and twenty callers would hold twenty
threads or queue behind each other, while the node must go on mapping. Here the callback only starts the job
(or joins one, see :class:`~lego_loam_py.core.io.CoalescingRunner`) and returns at once; the response is sent
when the job's future completes, from the thread that completes it.
"""
from __future__ import annotations

import threading
from concurrent.futures import Future
from typing import Any, Callable

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

__all__ = ['create_deferred_service', 'SERVICE_QUEUE_DEPTH']

# Requests a service keeps while they wait to be taken: as many callers as any robot's tools will have at once
# (rclpy's default of 10 silently drops the eleventh caller of a busy service).
SERVICE_QUEUE_DEPTH = 100


def create_deferred_service(node, srv_type, name: str, start: Callable[[Any], Future],
                            fill: Callable[[Any, Future], None], callback_group=None):
    """A service ``name`` of ``srv_type`` on ``node``: ``start(request)`` returns a Future of the work, and
    ``fill(response, future)`` writes the finished work into the response, which is then sent."""
    waiting: dict[int, Future] = {}
    lock = threading.Lock()

    def callback(request, response):
        future = start(request)
        with lock:
            waiting[id(response)] = future
        return response

    qos = QoSProfile(depth=SERVICE_QUEUE_DEPTH, history=HistoryPolicy.KEEP_LAST,
                     reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
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
            try:
                send_now(response, header)
            except Exception:   # the node is shutting down: nobody is left to answer
                pass

        future.add_done_callback(done)

    service.send_response = send_response   # rclpy's executor sends what the callback returned through this
    return service
