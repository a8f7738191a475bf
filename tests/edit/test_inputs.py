"""Edit inputs from files: regions, UV maps (.obj / .npy), correspondence pairs."""
import numpy as np
import pytest

from neumesh_core.edit.inputs import read_pairs, read_region, read_uvs
from neumesh_core.errors import EditError


def write_obj(path, vertices, faces, face_uv):
    """An .obj with one vt per face corner (as exporters write UV seams)."""
    with open(path, "w") as fh:
        for v in vertices:
            fh.write(f"v {v[0]} {v[1]} {v[2]}\n")
        for uv in np.asarray(face_uv).reshape(-1, 2):
            fh.write(f"vt {uv[0]} {uv[1]}\n")
        for i, f in enumerate(np.asarray(faces)):
            fh.write("f " + " ".join(f"{f[c] + 1}/{3 * i + c + 1}" for c in range(3)) + "\n")


def test_regions_from_text_and_npy(tmp_path):
    (tmp_path / "r.txt").write_text("# the blade\n5, 3 3\n9\n\n12 # end\n")
    assert read_region(str(tmp_path / "r.txt"), 20).tolist() == [3, 5, 9, 12]
    mask = np.zeros(20, bool)
    mask[[1, 4]] = True
    np.save(tmp_path / "m.npy", mask)
    assert read_region(str(tmp_path / "m.npy"), 20).tolist() == [1, 4]
    np.save(tmp_path / "i.npy", np.array([[7, 2], [2, 0]]))
    assert read_region(str(tmp_path / "i.npy"), 20).tolist() == [0, 2, 7]
    (tmp_path / "bad.txt").write_text("1 2 x\n")
    with pytest.raises(EditError, match="other than numbers"):
        read_region(str(tmp_path / "bad.txt"), 20)
    with pytest.raises(EditError, match="not found"):
        read_region(str(tmp_path / "nope.txt"), 20)
    with pytest.raises(EditError, match=r"\[0, 10\)"):
        read_region(str(tmp_path / "r.txt"), 10)


def test_uvs_from_an_obj_keep_one_uv_per_corner(tmp_path):
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    face_uv = np.array([[[0, 0], [1, 0], [1, 1]], [[0.5, 0], [1, 1], [0, 1]]])   # vertex 0: two UVs (seam)
    write_obj(tmp_path / "m.obj", v, faces, face_uv)
    uv = read_uvs(str(tmp_path / "m.obj"), 4)
    assert uv.vertex.tolist() == [0, 1, 2, 0, 2, 3]
    assert np.allclose(uv.uv, face_uv.reshape(-1, 2))
    with pytest.raises(EditError, match="has 4 vertices but the field has 5"):
        read_uvs(str(tmp_path / "m.obj"), 5)
    (tmp_path / "nouv.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(EditError, match="no UV index"):
        read_uvs(str(tmp_path / "nouv.obj"), 3)
    np.save(tmp_path / "uv.npy", np.random.default_rng(0).random((4, 2)))
    assert read_uvs(str(tmp_path / "uv.npy"), 4).vertex.tolist() == [0, 1, 2, 3]
    with pytest.raises(EditError, match=r"\(5, 2\)"):
        read_uvs(str(tmp_path / "uv.npy"), 5)


def test_pairs_files(tmp_path):
    (tmp_path / "p.txt").write_text("1 2\n3 4\n5 6\n")
    assert read_pairs(str(tmp_path / "p.txt")).shape == (3, 2)
    (tmp_path / "q.txt").write_text("0 0 0 1 1 1\n1 0 0 2 1 1\n0 1 0 1 2 1\n")
    assert read_pairs(str(tmp_path / "q.txt")).shape == (3, 6)
    (tmp_path / "r.txt").write_text("1 2 3\n")
    with pytest.raises(EditError, match="rows of 2"):
        read_pairs(str(tmp_path / "r.txt"))
