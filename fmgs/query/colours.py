"""Colour words in a query: its canonical form and its colour contrasts (fmgs.query.presence).

Text encoders place "green cube" close to "red cube" (MiniLM: 0.79), so a scene's red cube answers a
query for a green one unless presence asks the colour question on its own: the query's best Gaussians
must be closer to the query than to the same query in every other colour. Colour synonyms ("scarlet",
"crimson") are first mapped to their group's plain word, so a query is never contrasted with a
synonym of its own colour and encoders that barely know the rarer word still see "red".

A colour word counts only as an adjective: followed by another word ("orange pyramid" names a colour,
"orange" alone is the fruit).
"""

from __future__ import annotations

from typing import NamedTuple

COLOUR_GROUPS: tuple[tuple[str, ...], ...] = (
    ("red", "crimson", "scarlet", "maroon"),
    ("orange",),
    ("yellow", "golden"),
    ("green", "lime", "olive"),
    ("blue", "navy", "azure"),
    ("cyan", "turquoise", "teal", "aqua"),
    ("purple", "violet", "lilac", "lavender"),
    ("pink", "magenta"),
    ("white",),
    ("black",),
    ("grey", "gray", "silver"),
    ("brown", "beige", "tan"),
)
"""Each group's first word is its plain name; a query is contrasted with the other groups' plain names."""

_GROUP = {w: i for i, g in enumerate(COLOUR_GROUPS) for w in g}


class ColourProbe(NamedTuple):
    """The presence texts of one query."""

    canonical: str
    """The query with its colour word replaced by the group's plain word (the query itself when it
    names no colour)."""
    contrasts: tuple[str, ...]
    """The canonical query in every other group's colour; empty when it names no colour."""


def colour_probe(text: str) -> ColourProbe:
    """Canonical form and contrasts of ``text``: the first colour adjective (a colour word followed by
    another word) is the one contrasted; case and spacing are normalised only where it is replaced."""
    words = text.split()
    for i, w in enumerate(words[:-1]):
        g = _GROUP.get(w.lower())
        if g is None:
            continue

        def with_colour(h: int, i: int = i) -> str:
            return " ".join([*words[:i], COLOUR_GROUPS[h][0], *words[i + 1 :]])

        contrasts = tuple(with_colour(h) for h in range(len(COLOUR_GROUPS)) if h != g)
        return ColourProbe(with_colour(g), contrasts)
    return ColourProbe(text, ())
