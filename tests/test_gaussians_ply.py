import struct

import pytest
import torch

from ragsplat.gaussians import init_grid
from ragsplat.ply import load_ply, save_ply


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_ply_round_trip(tmp_path, degree):
    s = init_grid(0, 1, 0, 1, -1.0, 0.25, degree=degree)
    g = torch.Generator().manual_seed(degree)
    with torch.no_grad():
        for p in s.values():
            p.copy_(torch.randn(p.shape, generator=g))
    path = save_ply(tmp_path / "pc.ply", s)
    back = load_ply(path)
    assert set(back) == set(s.keys())
    for k in s:
        assert torch.equal(back[k], s[k].detach()), k


def test_ply_layout_is_3dgs(tmp_path):
    s = init_grid(0, 1, 0, 0.5, -1.0, 0.5, degree=1)  # 2 Gaussians, 3 rest coefficients per channel
    with torch.no_grad():
        s["shN"].copy_(torch.arange(18.0).reshape(2, 3, 3))  # [N, coeff, channel]
        s["opacities"].copy_(torch.tensor([-1.5, 2.0]))
    raw = save_ply(tmp_path / "pc.ply", s).read_bytes()
    header, body = raw.split(b"end_header\n")
    names = [line.split()[-1].decode() for line in header.splitlines() if line.startswith(b"property float")]
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert names[9:18] == [f"f_rest_{i}" for i in range(9)]
    assert names[18:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert b"format binary_little_endian 1.0" in header and b"element vertex 2" in header
    row0 = struct.unpack("<26f", body[:104])
    # f_rest channel-major: R of coeffs 0..2, then G, then B (3DGS's features_rest.transpose(1, 2))
    assert list(row0[9:18]) == [0.0, 3.0, 6.0, 1.0, 4.0, 7.0, 2.0, 5.0, 8.0]
    assert row0[18] == -1.5 and row0[3:6] == (0.0, 0.0, 0.0) and row0[22:26] == (1.0, 0.0, 0.0, 0.0)
    assert len(body) == 2 * 26 * 4


def test_ply_rejects_other_files(tmp_path):
    (tmp_path / "a.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    with pytest.raises(ValueError, match="binary_little_endian"):
        load_ply(tmp_path / "a.ply")
    (tmp_path / "b.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1\n"
                                     b"property float x\nend_header\n\0\0\0\0")
    with pytest.raises(ValueError, match="3DGS layout"):
        load_ply(tmp_path / "b.ply")
    s = init_grid(0, 1, 0, 1, -1.0, 0.5, degree=0)
    raw = save_ply(tmp_path / "c.ply", s).read_bytes()
    (tmp_path / "c.ply").write_bytes(raw[:-8])
    with pytest.raises(ValueError, match="truncated"):
        load_ply(tmp_path / "c.ply")
    (tmp_path / "d.ply").write_bytes(b"solid x\n")
    with pytest.raises(ValueError, match="not a PLY"):
        load_ply(tmp_path / "d.ply")
