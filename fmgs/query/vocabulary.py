"""Everyday things and stuff: the negatives a presence score contrasts a query with (fmgs.query.presence).

Broad on purpose: the more kinds of things the vocabulary names, the likelier the scene's own content
has a name in it that beats an absent query at the query's best Gaussians. Plain singular nouns, the
way a person names what they look for.
"""

from __future__ import annotations

_SINGLE_WORDS = """
    apple backpack bag ball banana basket bathtub bed bench bicycle bin blanket book bookshelf bottle
    bowl box bread brick bucket building bus cabinet cake camera can candle car carpet cat ceiling
    chair clock cloth computer cone counter cup cupboard curtain cushion desk dog door drawer dress
    egg fan fence flower floor folder fork fridge glass glove grass guitar hat headphones helmet
    house jacket jar jug kettle key keyboard knife ladder lamp laptop leaf lemon light magazine
    microwave mirror monitor motorcycle mouse mug napkin newspaper notebook orange oven painting pan
    paper pen pencil phone piano picture pillow pipe plant plate pot printer pumpkin radiator remote
    road rock roof rope rug scissors screen shelf shirt shoe sign sink skateboard sock sofa speaker
    spoon stairs stone stool suitcase table tablet teapot telephone television tile toaster toilet
    tomato tool towel toy tray tree truck umbrella vase wall wallet watch water window wine wood
    sky cloud mountain sand snow sea river bridge street sidewalk pole wire cable tire wheel engine
    statue sculpture fountain column arch balcony garden hedge bush flowerpot vegetable fruit meat
    cheese sandwich pizza cookie chocolate coffee tea bottlecap lid handle button switch socket
    hanger basketball football racket bat glasses ring necklace bracelet earring coin card
    ticket poster frame calendar map globe tissue soap shampoo toothbrush comb brush
    broom mop sponge hammer screwdriver wrench drill saw nail screw tape glue stapler marker
    crayon eraser ruler calculator battery charger lightbulb flashlight candlestick doll
    puzzle dice chessboard controller robot drone
"""
_PHRASES = ("teddy bear", "tennis racket", "board game", "candle holder", "traffic cone", "fire extinguisher")
VOCABULARY: tuple[str, ...] = (*_SINGLE_WORDS.split(), *_PHRASES)
