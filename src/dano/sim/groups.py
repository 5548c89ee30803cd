"""Pairs computed as one: partners of one shape kind stacked (a DANO's, or several DANOs' whose
points agree), so a step's program holds one copy of the contact per group instead of one per pair.

A robot brings many partners of a few kinds (the Panda: 9 convex meshes of 200 or 300 planes and
8 finger boxes). Each pair unrolled in Python made the step's program grow with the pairs: the
Panda sweeping a cube with the implicit step (18 pairs, 200 frames; `dano.sim.run.profile`) lowered
in 14.4 s and compiled in 52.1 s. Stacked leaf-wise along a leading axis (`stack`) and computed by
one loop over the group (`each`), its 4 groups lower in 3.8 s and compile in 21.3 s, run 200 frames
in 1.9 s instead of 2.8 s, and give the same trajectory; with the explicit step (100 frames) 3.3 s
and 17.9 s become 2.4 s and 12.1 s, the run the same (1.15 s).

Both steps also group across DANOs whose points agree in size (and, for the implicit step, budget:
`pair_groups`'s `danos`), each pair keeping its own DANO and velocities (`member_lookup`): the
paper's Fig. 5 (two 5000-point bunnies and a free sphere, 750 frames, `dano demo`'s scene) has five
pairs in three groups instead of five in the implicit step, and its rollout's program 17 800
StableHLO lines instead of 21 318, compiled in 10.5 s instead of 14.0 s (medians of three, one
after another), to the same trajectory (7e-13 m). Pairs of two DANOs are grouped where both sides
agree, fields included (`fields`: copies of one object): with a third bunny in that scene (nine
pairs in four groups, one of them its three bunny-bunny pairs) the program has 19 248 lines instead
of 34 841 and compiles in 14.8 s instead of 36.6 s (one run each, run 9.3 vs 8.5 s), to the same
trajectory (6e-13 m).
"""

from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp


def pair_groups(
    pair_list, mates: Sequence, other: Sequence[int], apart: Sequence = (), danos: Sequence = (), fields: Sequence = ()
) -> tuple[tuple[int, ...], ...]:
    """The pairs computed as one (indices into `pair_list`, in order of first appearance): those
    of one DANO whose partners (`mates`, `dano.sim.step.Partner`) move at known velocities (`other`
    -1: not solved for with the DANO) with shapes of one type and of the same array shapes (convex
    meshes of as many planes) and the same `apart` (a hashable per pair, if given); each other pair
    alone. Polytopes are not padded to the most planes: on the Panda (200 and 300) that cost the
    explicit step's rollout 20 % of its run time for no gain in compile time.

    With `danos` (a hashable per DANO: what its points are to the step, e.g. their array shapes and
    its active-set budget), pairs of different DANOs of equal `danos` are grouped too, and so are
    pairs whose primitive partner is solved for with the DANO (`other` >= 0; they are grouped
    only with such pairs): two bunnies of one point count on one floor are one floor pair in the
    program, and the sphere that hits them one more. With `fields` too (a hashable per DANO: its
    density field's structure), pairs of two DANOs are grouped where both sides agree (copies of
    one object: N of them make N (N - 1) / 2 pairs, one copy in the program); else each is alone."""
    keys: dict = {}
    apart = tuple(apart) or (None,) * len(pair_list)
    for j, ((i, _, _), mate, o, tag) in enumerate(zip(pair_list, mates, other, apart, strict=True)):
        if mate.shape is None and danos and fields and mate.dano >= 0:
            key = ("dano", danos[i], fields[i], danos[mate.dano], fields[mate.dano], tag)
        elif mate.shape is None or (o >= 0 and not danos):
            key = ("alone", j)
        else:
            key = (danos[i] if danos else i, o >= 0, tag, signature(mate.shape))
        keys.setdefault(key, []).append(j)
    return tuple(tuple(g) for g in keys.values())


def signature(tree) -> tuple:
    """A pytree's structure and its leaves' array shapes and dtypes (hashable): what must agree for
    trees to be stacked (`stack`) and computed by one program."""
    leaves, structure = jax.tree_util.tree_flatten(tree)
    return structure, tuple((jnp.shape(x), jnp.result_type(x)) for x in leaves)


def points_key(state) -> tuple:
    """A DANO's points as `pair_groups` compares them (`danos`): their structure, shapes and dtypes
    (`DanoState`'s points, normals and shares)."""
    return signature((state.points, state.normals, state.shares))


def member_lookup(keys: Sequence[int], value: Callable[[int], Any]) -> Callable[[Any], Any]:
    """Inside a group's loop (`each`): member m -> value(keys[m]) (a pytree per key, e.g. a DANO's
    contact data and frame). Closed over where every member has one key (one DANO's group, as a
    program without groups across DANOs has it); else read from the stack of the distinct keys'
    values, each stored once however many members share it."""
    if len(set(keys)) == 1:
        one = value(keys[0])
        return lambda m: one
    distinct = list(dict.fromkeys(keys))
    which = jnp.asarray([distinct.index(k) for k in keys])
    table = stack([value(k) for k in distinct])
    return lambda m: jax.tree_util.tree_map(lambda x: x[which[m]], table)


def stack(trees: Sequence):
    """Pytrees of one structure stacked leaf-wise along a new leading axis."""
    return jax.tree_util.tree_map(lambda *x: jnp.stack([jnp.asarray(v) for v in x]), *trees)


def each(fn: Callable, *args) -> Any:
    """fn over the leading axis of `args` (a group's stacked pairs), results stacked: a loop
    (`lax.map`), so the program holds one copy of fn and a pair's `lax.cond` (its broad phase) still
    skips its work; for a group of one, fn itself on the one pair. (A loop, not `vmap`: on the
    Panda sweeping a cube, its meshes padded into one group, the loop compiled in 23 s and ran 200
    frames in 3.4 s, `vmap` in 27 s and 4.7 s: batched small products are slower on a CPU than a
    loop of them.)"""
    if jax.tree_util.tree_leaves(args)[0].shape[0] == 1:
        return jax.tree_util.tree_map(lambda x: x[None], fn(*jax.tree_util.tree_map(lambda x: x[0], args)))
    return jax.lax.map(lambda a: fn(*a), args)
