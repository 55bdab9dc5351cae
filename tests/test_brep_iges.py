"""Named CAD files are the same for the same shapes: IGES name entities in a fixed order without
moving any name, STEP assembly occurrences numbered per file."""
from __future__ import annotations

from bonecad.occ import brep


def _face_names(model) -> list[str]:
    """The name of every named entity, in model order (through its 406 property)."""
    out = []
    for index in range(1, model.NbEntities() + 1):
        entity = model.Entity(index)
        if entity.TypeNumber() == 406 or not entity.NbProperties():
            continue
        found = entity.Properties()
        found.Start()
        while found.More():
            if found.Value().TypeNumber() == 406:
                out.append(found.Value().Value().ToCString())
            found.Next()
    return out


def test_name_entities_follow_the_named_entities_and_every_name_stays_on_its_entity():
    from OCP.BRepPrimAPI import BRepPrimAPI_MakeBox
    from OCP.IGESCAFControl import IGESCAFControl_Writer

    box = BRepPrimAPI_MakeBox(10.0, 20.0, 30.0).Shape()
    names = [(f"face_{i}", face) for i, face in enumerate(brep.faces(box))]
    brep.iges_settings()
    writer = IGESCAFControl_Writer()
    writer.SetNameMode(True)
    assert writer.Transfer(brep._xcaf_document(box, "box", names))
    model = writer.Model()
    before = _face_names(model)
    assert sorted(before) == sorted(["box"] + [n for n, _ in names])
    brep.order_name_entities(model)
    assert _face_names(model) == before
    slots = [model.Entity(i) for i in range(1, model.NbEntities() + 1) if model.Entity(i).TypeNumber() == 406]
    assert [s.Value().ToCString() for s in slots] == before


def test_a_named_tree_written_twice_in_one_process_gives_the_same_files(tmp_path):
    from OCP.BRepPrimAPI import BRepPrimAPI_MakeBox, BRepPrimAPI_MakeSphere

    from bonecad.occ.exchange import write_iges, write_step

    tree = ("parts", [("box", BRepPrimAPI_MakeBox(10.0, 20.0, 30.0).Shape()),
                      ("more", [("sphere", BRepPrimAPI_MakeSphere(5.0).Shape())])])
    for write, suffix in ((write_step, "step"), (write_iges, "iges")):
        first = write(tree, tmp_path / f"first.{suffix}").read_bytes()
        assert write(tree, tmp_path / f"second.{suffix}").read_bytes() == first, suffix
