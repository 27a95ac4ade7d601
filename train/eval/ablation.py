"""The named ablation of the descriptions: tactile adjectives written by hand.

vtzero's database once described every reference class by how it feels ("a cube of smooth
steel, rigid and unyielding"), so the sentence the VLM read already said "hard" or "soft" and
the paper's mechanism (the VLM infers the feel from object *names*) was bypassed. The shipped
database names objects only (:mod:`edge.core.descriptions` refuses tactile words); these old
sentences survive here for one purpose: ``vt-train eval-vlm --conditions
vq_top3_adjectives`` measures what hand-written tactile labels would add on top of the
method. They are never written into a model directory.
"""

from __future__ import annotations

TACTILE_ADJECTIVES: dict[str, str] = {
    "wood_cube": "a cube of hard wood that does not give at all",
    "stainless_cube": "a cube of smooth steel, rigid and unyielding",
    "aluminium_cube": "a cube of light metal, rigid and smooth",
    "acrylic_cube": "a cube of clear hard plastic, rigid and slick",
    "rubber_cube": "a firm rubber block that springs straight back",
    "silicone_cube": "a soft silicone block, springy and grippy",
    "sponge_cube": "a squashy sponge that gives easily and stiffens as it compresses",
    "cork_cube": "a block of cork, firm with a slight give",
    "eraser": "a rubber eraser, firm and slightly springy",
    "glass_marble": "a small glass marble, hard and perfectly round",
    "rubber_ball": "a bouncy rubber ball, round and springy",
    "foam_ball": "a light foam ball that squashes softly",
    "gelatin_soft": "a soft wobbly gelatin that yields and slowly settles",
    "tofu_firm": "a block of firm tofu, soft, moist and slightly crumbly",
    "marshmallow": "a marshmallow, very soft, spongy and slow to spring back",
    "bread_cube": "a cube of bread, airy and soft, crushing under pressure",
    "otedama": "a bean bag, soft and granular, it flows and stays squashed",
    "clay": "a lump of modelling clay, dense and dough-like, it keeps its dents",
    "kiwi_piece": "a piece of ripe kiwi fruit, soft, juicy and slippery",
    "apple_piece": "a piece of raw apple, crisp and firm",
    "banana_piece": "a slice of banana, soft, smooth and mushy",
    "cheese_cube": "a cube of processed cheese, soft, smooth and slightly elastic",
    "quail_egg_boiled": "a boiled quail egg, smooth, springy and round",
    "grape": "a grape, round, taut and juicy",
    "gummy_candy": "a gummy candy, chewy and rubbery",
    "dango": "a rice dumpling, soft, sticky and doughy",
    "cotton_ball": "a cotton ball, airy and feather-soft",
    "gelatin_hard": "a firm gelatin that gives a little and settles slowly",
    "cherry_tomato": "a cherry tomato, round, taut and springy",
    "yokan": "a block of sweet bean jelly, dense, smooth and slightly soft",
    "plastic_cube": "a cube of hard plastic, rigid with a faint give",
    "soap_bar": "a bar of soap, hard and smooth with a slippery skin",
}
