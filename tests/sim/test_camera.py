from edge.sim.camera import render
from edge.sim.catalogue import names


def test_look_alike_pairs_give_the_same_picture():
    for name in names("foodreplica") + names("cube"):
        twin = name.removeprefix("resin_replica_").replace("raw_", "boiled_", 1)
        if twin != name:
            assert render(name) == render(twin), name
    assert render("wood_cube") != render("stainless_cube")
    assert render("raw_kiri_mochi") != render("raw_kabocha_squash")
