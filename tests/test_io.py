import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest import DATA_DIR
from vrnet_ext.geometry.io import PointCloudError, read_points, read_transform, write_ply

SCENES = DATA_DIR / "scenes"


@pytest.fixture
def points():
    return np.random.default_rng(0).normal(size=(57, 3)).astype(np.float32)


def test_ply_binary_round_trip(tmp_path, points):
    write_ply(tmp_path / "a.ply", points)
    np.testing.assert_array_equal(read_points(tmp_path / "a.ply"), points)


def test_ply_ascii_with_other_elements_and_properties(tmp_path, points):
    header = ("ply\nformat ascii 1.0\ncomment made by hand\nelement camera 2\nproperty float px\n"
              f"element vertex {len(points)}\nproperty uchar red\nproperty double z\nproperty float y\n"
              "property float x\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n")
    rows = "1.5\n2.5\n" + "".join(f"7 {z!r} {y!r} {x!r}\n" for x, y, z in points.tolist()) + "3 0 1 2\n"
    (tmp_path / "b.ply").write_text(header + rows)
    np.testing.assert_allclose(read_points(tmp_path / "b.ply"), points, rtol=1e-6)


def test_ply_big_endian_with_extra_properties(tmp_path, points):
    dtype = np.dtype([("x", ">f8"), ("y", ">f8"), ("z", ">f8"), ("intensity", ">u2")])
    table = np.zeros(len(points), dtype)
    for i, a in enumerate("xyz"):
        table[a] = points[:, i]
    header = (f"ply\nformat binary_big_endian 1.0\nelement vertex {len(points)}\nproperty double x\n"
              "property double y\nproperty double z\nproperty ushort intensity\nend_header\n")
    (tmp_path / "c.ply").write_bytes(header.encode() + table.tobytes())
    np.testing.assert_array_equal(read_points(tmp_path / "c.ply"), points)


@pytest.mark.parametrize("mode", ["ascii", "binary"])
def test_pcd(tmp_path, points, mode):
    header = ("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z normal\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 3\n"
              f"WIDTH {len(points)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(points)}\nDATA {mode}\n")
    table = np.concatenate([points, np.ones((len(points), 3), np.float32)], axis=1)
    body = ("".join(" ".join(repr(v) for v in row) + "\n" for row in table.tolist()).encode()
            if mode == "ascii" else table.astype("<f4").tobytes())
    (tmp_path / "d.pcd").write_bytes(header.encode() + body)
    np.testing.assert_allclose(read_points(tmp_path / "d.pcd"), points, rtol=1e-6)


def test_npy_text_csv_and_kitti(tmp_path, points):
    np.save(tmp_path / "e.npy", np.concatenate([points, points[:, :1]], axis=1).astype(np.float64))
    np.savetxt(tmp_path / "f.xyz", points, header="x y z")
    np.savetxt(tmp_path / "g.csv", points, delimiter=",")
    np.concatenate([points, np.zeros((len(points), 1), np.float32)], axis=1).astype("<f4").tofile(tmp_path / "h.bin")
    for name in ("e.npy", "f.xyz", "g.csv", "h.bin"):
        got = read_points(tmp_path / name)
        assert got.dtype == np.float64 and got.shape == points.shape, name
        np.testing.assert_allclose(got, points, rtol=1e-6, err_msg=name)


def test_bad_files_raise_clear_errors(tmp_path, points):
    write_ply(tmp_path / "ok.ply", points)
    data = (tmp_path / "ok.ply").read_bytes()
    (tmp_path / "truncated.ply").write_bytes(data[:-5])
    (tmp_path / "noz.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                                      "end_header\n0 0\n1 1\n2 2\n")
    (tmp_path / "noheader.ply").write_bytes(b"ply\nformat ascii 1.0\n" + b"0 0 0\n" * 10)
    (tmp_path / "compressed.pcd").write_text("FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 3\nDATA binary_compressed\n")
    bad = points.copy()
    bad[4, 1] = np.nan
    np.savetxt(tmp_path / "nan.xyz", bad)
    np.savetxt(tmp_path / "two.xyz", points[:2])
    np.savetxt(tmp_path / "words.xyz", [["a", "b", "c"]], fmt="%s")
    np.save(tmp_path / "flat.npy", points[:, 0])
    (tmp_path / "odd.bin").write_bytes(b"\0" * 18)
    cases = {"truncated.ply": "truncated", "noz.ply": "x, y and z", "noheader.ply": "end_header",
             "compressed.pcd": "binary_compressed", "nan.xyz": "NaN or Inf", "two.xyz": "at least 3",
             "words.xyz": "numbers", "flat.npy": "(N, >=3)", "odd.bin": "16 bytes", "missing.ply": "no such file",
             "cloud.obj": "unknown extension"}
    for name, message in cases.items():
        with pytest.raises(PointCloudError, match=message) as info:
            read_points(tmp_path / name)
        assert name in str(info.value)


def test_read_transform(tmp_path):
    T = np.eye(4)
    T[:3, 3] = [1, 2, 3]
    (tmp_path / "t.txt").write_text("# a header line\n" + "\n".join(" ".join(f"{v:.6e}" for v in row) for row in T))
    np.testing.assert_allclose(read_transform(tmp_path / "t.txt"), T)
    (tmp_path / "short.txt").write_text("1 0 0 0 1 0 0 0 1")
    with pytest.raises(PointCloudError, match="16 numbers"):
        read_transform(tmp_path / "short.txt")
    (tmp_path / "scaled.txt").write_text("\n".join(" ".join(str(v) for v in row) for row in 2 * np.eye(4)))
    with pytest.raises(PointCloudError, match="rigid"):
        read_transform(tmp_path / "scaled.txt")
    (tmp_path / "mirror.txt").write_text("\n".join(" ".join(str(v) for v in row) for row in np.diag([1, 1, -1, 1])))
    with pytest.raises(PointCloudError, match="det"):
        read_transform(tmp_path / "mirror.txt")
    rounded = Rotation.from_euler("zyx", [30, 10, -20], degrees=True).as_matrix() + 1.3e-4  # a 4-digit log
    T[:3, :3] = rounded
    (tmp_path / "rounded.txt").write_text("\n".join(" ".join(f"{v:.9f}" for v in row) for row in T))
    np.testing.assert_allclose(read_transform(tmp_path / "rounded.txt"), T, atol=1e-9)


@pytest.mark.skipif(not (SCENES / "lidar_pair" / "source.ply").exists(), reason=f"real scans not found under {SCENES}")
def test_real_scans():
    lidar = read_points(SCENES / "lidar_pair" / "source.ply")
    assert lidar.shape == (69792, 3)
    kitchen = read_points(SCENES / "3dmatch_redkitchen" / "cloud_bin_0.ply")
    assert kitchen.shape == (258342, 3) and float(np.abs(kitchen).max()) < 10.0  # metres, indoor
    T = read_transform(SCENES / "lidar_pair" / "T_target_source.txt")
    assert abs(np.linalg.det(T[:3, :3]) - 1) < 1e-5


def test_hostile_headers_and_arrays_raise_clear_errors(tmp_path, points):
    cases = {}
    cases["negative.ply"] = ("ply\nformat ascii 1.0\nelement vertex -3\nproperty float x\nproperty float y\n"
                             "property float z\nelement face 1\nproperty list uchar int v\nend_header\n1 2 3\n3 0 1 2\n")
    cases["negative.pcd"] = ("# .PCD v0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH -2\nHEIGHT 1\n"
                             "POINTS -2\nDATA ascii\n1 2 3\n")
    cases["short_property.ply"] = "ply\nformat ascii 1.0\nelement vertex 3\nproperty\nend_header\n1 2 3\n"
    cases["x_twice.ply"] = ("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float x\n"
                            "property float y\nproperty float z\nend_header\n1 2 3 4\n")
    pcd_count_2 = "# .PCD v0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 2 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 1\n"
    cases["count2.pcd"] = pcd_count_2 + "DATA ascii\n1 1 2 3\n"
    cases["count2_binary.pcd"] = pcd_count_2 + "DATA binary\n" + "\0" * 16
    for name, text in cases.items():
        (tmp_path / name).write_text(text)
    huge = tmp_path / "huge.npy"
    with open(huge, "wb") as f:  # a header promising 10^10 x 3 float64 (224 GiB) and 24 bytes of data
        np.lib.format.write_array_header_1_0(f, {"descr": "<f8", "fortran_order": False, "shape": (10**10, 3)})
        f.write(np.zeros(3).tobytes())
    np.save(tmp_path / "complex.npy", points.astype(np.complex64) + 1j)
    np.save(tmp_path / "bool.npy", points > 0)
    for name, message in [("negative.ply", "negative"), ("negative.pcd", "negative"), ("short_property.ply", "property"),
                          ("x_twice.ply", "name x more than once"), ("count2.pcd", "COUNT of x must be 1"),
                          ("count2_binary.pcd", "COUNT of x must be 1"),
                          ("huge.npy", "not a readable"), ("complex.npy", "real-valued"), ("bool.npy", "real-valued")]:
        with pytest.raises(PointCloudError, match=message) as info:
            read_points(tmp_path / name)
        assert str(tmp_path / name) in str(info.value)


def test_pcd_comment_that_mentions_data_is_a_comment(tmp_path, points):
    header = ("# .PCD v0.7 - DATA written by hand\n# DATA binary would be faster\nVERSION 0.7\nFIELDS x y z\n"
              "SIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
              f"WIDTH {len(points)}\nHEIGHT 1\nPOINTS {len(points)}\nDATA ascii\n")
    (tmp_path / "c.pcd").write_text(header + "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in points.tolist()))
    np.testing.assert_allclose(read_points(tmp_path / "c.pcd"), points, rtol=1e-6)


def test_read_transform_of_a_binary_file_names_the_file(tmp_path, points):
    write_ply(tmp_path / "scan.ply", points)
    with pytest.raises(PointCloudError, match="scan.ply"):
        read_transform(tmp_path / "scan.ply")


def test_ascii_ply_is_read_without_per_line_python_objects(tmp_path):
    # 400k vertices, ~17 MB of text: peak memory must stay a small multiple of the file (was ~16x)
    import resource
    import subprocess
    import sys

    rng = np.random.default_rng(0)
    cloud = rng.normal(size=(400_000, 3))
    path = tmp_path / "big.ply"
    header = ("ply\nformat ascii 1.0\nelement vertex 400000\nproperty float x\nproperty float y\n"
              "property float z\nend_header\n")
    with open(path, "w") as f:
        f.write(header)
        np.savetxt(f, cloud, fmt="%.6f")
    size_mb = path.stat().st_size / 2**20
    code = ("import resource, sys; from vrnet_ext.geometry.io import read_points; "
            "base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss; p = read_points(sys.argv[1]); "
            "print(p.shape[0], (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base) / 1024)")
    out = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, timeout=300)
    rows, extra_mb = out.stdout.split()
    assert int(rows) == 400_000
    assert float(extra_mb) < 4 * size_mb, (extra_mb, size_mb)


def test_georeferenced_coordinates_keep_their_precision(tmp_path):
    """UTM-sized coordinates: float32 spacing there is 0.5 m. Reading (float64) and writing (double
    when float would blur the cloud) keep them."""
    cloud = np.random.default_rng(0).normal(size=(100, 3)) * 10 + np.array([5e5, 5e6, 100.0])
    np.save(tmp_path / "utm.npy", cloud)
    np.testing.assert_array_equal(read_points(tmp_path / "utm.npy"), cloud)
    write_ply(tmp_path / "utm.ply", cloud)
    np.testing.assert_array_equal(read_points(tmp_path / "utm.ply"), cloud)
    write_ply(tmp_path / "near.ply", cloud - cloud.mean(0))  # near the origin: float is enough
    assert b"property float x" in (tmp_path / "near.ply").read_bytes()[:200]


def test_as_points_takes_arrays_tensors_point_clouds_and_paths(tmp_path):
    import torch

    from vrnet_ext.geometry.io import as_points

    cloud = np.random.default_rng(1).normal(size=(20, 3))
    np.save(tmp_path / "c.npy", cloud)

    class PointCloud:  # what Open3D's PointCloud offers: a `points` attribute convertible by numpy
        points = cloud.tolist()

    for given in (cloud, cloud.astype(np.float32), torch.as_tensor(cloud), PointCloud(), tmp_path / "c.npy",
                  str(tmp_path / "c.npy")):
        got = as_points(given, "source")
        assert got.dtype == np.float64 and got.shape == (20, 3)
        np.testing.assert_allclose(got, cloud, rtol=1e-6)
    with pytest.raises(ValueError, match="source must have shape"):
        as_points(np.zeros((4, 4)), "source")
    with pytest.raises(ValueError, match="source needs at least 3 points"):
        as_points(np.zeros((2, 3)), "source")
    with pytest.raises(ValueError, match="source has NaN"):
        as_points(np.full((5, 3), np.nan), "source")
    with pytest.raises(ValueError, match="source must be an"):
        as_points(object(), "source")


@pytest.mark.parametrize("kind", ["ply", "pcd"])
def test_ascii_header_counts_do_not_size_allocations(tmp_path, kind):
    """A 3-line ASCII file whose header claims 10^10 points: a truncation error naming the file, at once."""
    if kind == "ply":
        text = "ply\nformat ascii 1.0\nelement vertex 10000000000\nproperty float x\nproperty float y\n" \
               "property float z\nend_header\n0 0 0\n1 1 1\n2 2 2\n"
    else:
        text = "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 10000000000\nHEIGHT 1\n" \
               "POINTS 10000000000\nDATA ascii\n0 0 0\n1 1 1\n2 2 2\n"
    path = tmp_path / f"claims.{kind}"
    path.write_text(text)
    with pytest.raises(PointCloudError, match=f"{path.name}.*truncated|{path.name}.*promises"):
        read_points(path)


def test_a_transform_file_is_not_a_cloud(tmp_path):
    np.savetxt(tmp_path / "T.txt", np.eye(4))
    with pytest.raises(PointCloudError, match="T.txt.*4x4 transform, not a point cloud"):
        read_points(tmp_path / "T.txt")


def test_an_npz_archive_named_npy_is_named_in_the_error(tmp_path):
    np.savez(tmp_path / "a.npz", points=np.zeros((5, 3)))
    (tmp_path / "a.npz").rename(tmp_path / "a.npy")
    with pytest.raises(PointCloudError, match="a.npy.*npz archive"):
        read_points(tmp_path / "a.npy")


def test_a_csv_header_row_is_skipped(tmp_path, points):
    np.savetxt(tmp_path / "h.csv", points, delimiter=",", header="x,y,z", comments="")
    np.testing.assert_allclose(read_points(tmp_path / "h.csv"), points, rtol=1e-6)
    np.savetxt(tmp_path / "e.xyz", np.array([[1e-3, 2.5e2, -3e1]] * 4))  # exponents are numbers, not a header
    assert read_points(tmp_path / "e.xyz").shape == (4, 3)


def test_outputs_get_ordinary_file_permissions(tmp_path):
    import os
    import stat

    write_ply(tmp_path / "new.ply", np.zeros((4, 3)))
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE((tmp_path / "new.ply").stat().st_mode) == 0o666 & ~umask
    os.chmod(tmp_path / "new.ply", 0o640)
    write_ply(tmp_path / "new.ply", np.ones((4, 3)))  # replacing keeps the file's mode
    assert stat.S_IMODE((tmp_path / "new.ply").stat().st_mode) == 0o640


def test_a_ply_header_line_the_reader_does_not_know_is_refused_naming_it(tmp_path, points):
    write_ply(tmp_path / "good.ply", points)
    text = (tmp_path / "good.ply").read_bytes()
    for bad in (b"Property float x", b"proprety float x"):
        (tmp_path / "bad.ply").write_bytes(text.replace(b"property float x", bad, 1))
        with pytest.raises(PointCloudError, match=r"bad.ply: header line \d+ is not a PLY header line"):
            read_points(tmp_path / "bad.ply")


def test_text_rows_with_upper_case_exponents_keep_their_first_point(tmp_path, points):
    np.savetxt(tmp_path / "e.xyz", points, fmt="%.9E")
    np.testing.assert_allclose(read_points(tmp_path / "e.xyz"), points, rtol=1e-8)
    np.savetxt(tmp_path / "e.csv", points, fmt="%.9E", delimiter=",")
    assert read_points(tmp_path / "e.csv").shape == points.shape
    (tmp_path / "mixed.txt").write_text("1.0 2.0 x3\n" + "1 2 3\n" * 5)
    with pytest.raises(PointCloudError, match="mixed.txt: line 1 mixes numbers and words"):
        read_points(tmp_path / "mixed.txt")


def pcd_text(points, header_points, width=None, data="ascii"):
    width = header_points if width is None else width
    head = (f"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {width}\nHEIGHT 1\n"
            f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {header_points}\nDATA {data}\n").encode()
    if data == "ascii":
        return head + "".join(f"{x} {y} {z}\n" for x, y, z in points).encode()
    return head + points.astype("<f4").tobytes()


def test_pcd_counts_are_checked_against_the_whole_file(tmp_path, points):
    n = len(points)
    (tmp_path / "ok.pcd").write_bytes(pcd_text(points, n))
    assert read_points(tmp_path / "ok.pcd").shape == (n, 3)
    cases = {"more_rows.pcd": (pcd_text(points, n - 2), f"promises {n - 2} points, the data has {n} rows"),
             "width.pcd": (pcd_text(points, n, width=n + 1), "WIDTH x HEIGHT"),
             "extra_bytes.pcd": (pcd_text(points, n - 2, data="binary"), f"promises {n - 2} points of 12 bytes")}
    for name, (content, message) in cases.items():
        (tmp_path / name).write_bytes(content)
        with pytest.raises(PointCloudError, match=f"{name}: .*{re.escape(message)}"):
            read_points(tmp_path / name)


def write_log(path, blocks):
    path.write_text("".join(f"{i}\t {j}\t 60\n" + "".join(" ".join(f"{v:.9e}" for v in row) + "\n" for row in T)
                            for (i, j), T in blocks.items()))


def test_ground_truth_from_a_3dmatch_log_by_fragments_or_file_names(tmp_path):
    from vrnet_ext.geometry.io import read_ground_truth

    rng = np.random.default_rng(3)
    blocks = {}
    for pair in ((0, 4), (0, 10), (4, 10)):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3)
        blocks[pair] = T
    write_log(tmp_path / "gt.log", blocks)
    log = tmp_path / "gt.log"
    # block "i j" maps fragment j into fragment i: source j, target i as it is; source i, target j inverted
    np.testing.assert_allclose(read_ground_truth(log, fragments=(4, 0)), blocks[(0, 4)], atol=1e-8)
    np.testing.assert_allclose(read_ground_truth(log, fragments=(0, 4)), np.linalg.inv(blocks[(0, 4)]), atol=1e-8)
    named = read_ground_truth(log, tmp_path / "cloud_bin_10.ply", tmp_path / "cloud_bin_4.ply")
    np.testing.assert_allclose(named, blocks[(4, 10)], atol=1e-8)
    with pytest.raises(PointCloudError, match="gt.log: the 3DMatch log has no entry for fragments 1 and 2"):
        read_ground_truth(log, fragments=(1, 2))
    with pytest.raises(PointCloudError, match="gt.log: a 3DMatch log of 3 pairs"):
        read_ground_truth(log, "a.ply", "b.ply")
    write_log(tmp_path / "one.log", {(0, 4): blocks[(0, 4)]})
    np.testing.assert_allclose(read_ground_truth(tmp_path / "one.log"), blocks[(0, 4)], atol=1e-8)
    np.savetxt(tmp_path / "T.txt", blocks[(0, 4)])
    np.testing.assert_allclose(read_ground_truth(tmp_path / "T.txt", "cloud_bin_0.ply", "cloud_bin_4.ply"),
                               blocks[(0, 4)])
    with pytest.raises(PointCloudError, match="T.txt: fragments .* not a 3DMatch log"):
        read_ground_truth(tmp_path / "T.txt", fragments=(0, 4))
    with pytest.raises(PointCloudError, match="gt.log: a 4x4 transform needs 16 numbers, found 57 .*read_ground_truth"):
        read_transform(log)


def test_read_poses_takes_kitti_lines_flat_lines_and_blocks(tmp_path):
    from vrnet_ext.geometry.io import read_poses

    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3, 3)))
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, :3, :3] = q * np.sign(np.linalg.det(q))[:, None, None]
    poses[:, :3, 3] = rng.normal(size=(3, 3))
    def line(values):
        return " ".join(f"{v:.17g}" for v in values)

    layouts = {"kitti.txt": "\n".join(line(p[:3].ravel()) for p in poses),
               "flat.txt": "# poses\n" + "\n".join(line(p.ravel()) for p in poses),
               "blocks.txt": "\n\n".join("\n".join(line(row) for row in p) for p in poses)}
    for name, text in layouts.items():
        (tmp_path / name).write_text(text)
        np.testing.assert_allclose(read_poses(tmp_path / name, list('abc')), poses, atol=1e-12)
    with pytest.raises(PointCloudError, match="expected 2 poses"):
        read_poses(tmp_path / "kitti.txt", ["a", "b"])
    poses[1, 0, 0] = 3.0
    (tmp_path / "scaled.txt").write_text("\n".join(line(p.ravel()) for p in poses))
    with pytest.raises(PointCloudError, match="not a rigid transform"):
        read_poses(tmp_path / "scaled.txt", list("abc"))


def test_read_poses_chains_a_3dmatch_log_by_fragment_names(tmp_path):
    from vrnet_ext.geometry.io import read_poses

    poses = np.stack([np.eye(4)] + [np.eye(4) for _ in range(2)])
    for k in (1, 2):
        poses[k, :3, :3] = Rotation.from_rotvec([0.1 * k, -0.2, 0.3]).as_matrix()
        poses[k, :3, 3] = [k, 2.0 * k, -0.5]
    fragments = [7, 3, 12]  # the scans cloud_bin_7, cloud_bin_3, cloud_bin_12, in this order

    def block(a, b):  # fragment b into fragment a's frame, as gt.log writes it
        T = np.linalg.inv(poses[a]) @ poses[b]
        return f"{fragments[a]} {fragments[b]} 13\n" + "\n".join(" ".join(f"{v:.17g}" for v in row) for row in T)

    (tmp_path / "gt.log").write_text(block(0, 2) + "\n" + block(2, 1) + "\n")
    scans = [f"scans/cloud_bin_{i}.ply" for i in fragments]
    np.testing.assert_allclose(read_poses(tmp_path / "gt.log", scans), poses, atol=1e-12)
    with pytest.raises(PointCloudError, match="no chain of the log's pairs links scans/cloud_bin_5.ply"):
        read_poses(tmp_path / "gt.log", scans + ["scans/cloud_bin_5.ply"])
    with pytest.raises(PointCloudError, match="name the scans cloud_bin_<index> \\(room.ply is not\\)"):
        read_poses(tmp_path / "gt.log", scans[:2] + ["room.ply"])
