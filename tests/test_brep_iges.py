"""IGES names: the XCAF writer's name entities put in a fixed order without moving any name."""
from __future__ import annotations

from bonecad.io import brep


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
