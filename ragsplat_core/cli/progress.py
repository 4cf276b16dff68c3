"""The command layer's progress bars (tqdm on stderr) and its deferred interrupts."""

from __future__ import annotations

import contextlib
import signal


def bar(total: int, desc: str, unit: str = "it", initial: int = 0, disable: bool = False, leave: bool = True):
    """A tqdm bar on stderr; use as a context manager or call `.close()`."""
    from tqdm import tqdm

    return tqdm(total=total, initial=initial, desc=desc, unit=unit, disable=disable, leave=leave,
                dynamic_ncols=True)


def count_bar(desc: str, unit: str, disable: bool = False):
    """(bar, on_count): `on_count(done, total)` (e.g. `export.extract_bed`'s `on_block`) sets the bar to done
    of total; close the bar when done."""
    b = bar(1, desc, unit, disable=disable)

    def on_count(done: int, total: int) -> None:
        b.total = total
        b.update(done - b.n)

    return b, on_count


def training_bar(total: int, desc: str, initial: int = 0, disable: bool = False, leave: bool = True,
                 check=None):
    """(bar, on_step): `on_step(trainer)` advances the bar and shows loss, PSNR on the training view and
    the Gaussian count; pass it to `Trainer.train(on_step=...)`. `check()` (from `deferred_interrupts`) is
    called after every step."""
    b = bar(total, desc, "it", initial, disable, leave)

    def on_step(trainer) -> None:
        if check is not None:
            check()
        b.update(1)
        if trainer.step % 10 == 0 or trainer.step == total:
            last = trainer.last
            b.set_postfix(loss=f"{last['loss']:.4f}", psnr=f"{last['psnr']:.2f}", n=trainer.num_gaussians,
                          refresh=False)

    return b, on_step



@contextlib.contextmanager
def deferred_interrupts():
    """Within the block a first Ctrl-C or SIGTERM only takes note; the yielded `check()` then raises
    KeyboardInterrupt at a safe point (after a training step, so the trainer's checkpoint holds whole
    steps). A second one interrupts at once."""
    pending = []

    def note(signum, frame):
        if pending:
            raise KeyboardInterrupt
        pending.append(signum)

    def check() -> None:
        if pending:
            raise KeyboardInterrupt

    old = {s: signal.signal(s, note) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield check
    finally:
        for s, handler in old.items():
            signal.signal(s, handler)
