"""One module per seed experiment reproduced by ``bench/reproduce.py``.

Each module defines ``TITLE`` (its ``## …`` heading in ``bench/REPRODUCTION.md``) and
``run(ctx: Context) -> str``, which runs the experiment with the seed's protocol, writes its
PNGs into ``ctx.plots`` and returns the section's markdown (without the heading): the seed's
numbers and ours side by side, protocol differences, figures, and a one-line verdict.
"""
