"""Read ahead: the next input frames are decoded in a background thread while the current one
is processed (PNG/JPEG decoding and bag reading release the GIL, so on 2 cores it overlaps
with tracking instead of adding to it)."""
from __future__ import annotations

import queue
import threading
from typing import Iterable, Iterator, TypeVar

T = TypeVar("T")

_ITEM, _ERROR, _END = 0, 1, 2


def prefetch(items: Iterable[T], depth: int = 2) -> Iterator[T]:
    """Yield ``items`` in order, producing up to ``depth`` of them ahead in a thread.

    An exception raised while producing an item is raised here, at that item's place.
    Closing the generator early (``break``) stops the thread after the item it is on and
    waits (up to 5 s) for that."""
    if depth <= 0:
        yield from items
        return
    q: "queue.Queue" = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def put(msg) -> bool:
        while not stop.is_set():
            try:
                q.put(msg, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def work() -> None:
        try:
            for x in items:
                if not put((_ITEM, x)):
                    return
        except BaseException as e:          # handed to the consumer, raised there
            put((_ERROR, e))
            return
        put((_END, None))

    t = threading.Thread(target=work, name="prefetch", daemon=True)
    t.start()
    try:
        while True:
            kind, x = q.get()
            if kind == _ITEM:
                yield x
            elif kind == _ERROR:
                raise x
            else:
                return
    finally:
        stop.set()
        # let the thread finish the item it is reading, so that the source (a bag reader,
        # say) is not used by two threads when the caller iterates it again
        t.join(timeout=5.0)


def read_frames(frames: Iterable[T], progress: bool = True, total=None, max_frames=None,
                postfix=None) -> Iterator[T]:
    """The input of a run: ``frames`` read ahead (:func:`prefetch`), at most ``max_frames``,
    with a progress bar when ``progress`` (``postfix(n)`` -> dict shown beside it, called
    after each frame was handled)."""
    bar = None
    if progress:
        from tqdm import tqdm
        if total is None and hasattr(frames, "__len__"):
            total = len(frames)  # type: ignore[arg-type]
        if max_frames is not None and total is not None:
            total = min(total, max_frames)
        bar = tqdm(total=total, unit="frame", dynamic_ncols=True)
    n = 0
    try:
        for frame in prefetch(frames, 2):        # the next frames decode while this one runs
            if max_frames is not None and n >= max_frames:
                break
            yield frame
            n += 1
            if bar is not None:
                bar.update(1)
                if postfix is not None:
                    bar.set_postfix(**postfix(n), refresh=False)
    finally:
        if bar is not None:
            bar.close()
