"""Requests for one slow job (a map save), served by runs on a worker thread that coalesce what comes meanwhile: the
save_map service and the shutdown save of mapOptimization."""

from __future__ import annotations

__all__ = ['CoalescingRunner']


class CoalescingRunner:
    """Runs ``job`` on a worker thread when asked, one run at a time, and coalesces requests.

    :meth:`request` returns a :class:`concurrent.futures.Future` of a run's result (or its exception). With no
    run going on, a run starts at once; a request made while one is going on is answered by the next run,
    which starts as soon as the current one ends and serves every request made meanwhile. Twenty callers at
    once therefore cost two runs, and each gets a result from a run that started after it asked (or the one
    going on when it asked).
    """

    def __init__(self, job, name: str = 'job'):
        import threading

        self._job = job
        self._name = name
        self._lock = threading.Lock()
        self._running = None  # the Future of the run going on
        self._next = None  # the Future shared by the requests made meanwhile
        self.runs = 0

    def request(self):
        from concurrent.futures import Future

        with self._lock:
            if self._running is None:
                self._running = Future()
                self._start(self._running)
                return self._running
            if self._next is None:
                self._next = Future()
            return self._next

    def _start(self, future) -> None:
        import threading

        self.runs += 1
        threading.Thread(target=self._run, args=(future,), name=f'{self._name} run {self.runs}', daemon=True).start()

    def _run(self, future) -> None:
        result, error = None, None
        try:
            result = self._job()
        except BaseException as exc:  # handed to every caller
            error = exc
        # The runner is idle (or on its next run) before anyone hears of the result: a caller that asks again
        # at once gets a new run, and busy() is False once every caller has its answer.
        with self._lock:
            self._running, self._next = self._next, None
            if self._running is not None:
                self._start(self._running)
        if error is not None:
            future.set_exception(error)
        else:
            future.set_result(result)

    def busy(self) -> bool:
        with self._lock:
            return self._running is not None
