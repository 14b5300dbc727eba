"""TIFF files as other programs read them: OME-XML PhysicalSize* / Plane PositionZ (Fiji through
Bio-Formats, napari's OME readers, tifffile) and the TIFF resolution tags (ImageJ's own opener),
parsed here without cm2cl's reader; and cm2cl's reader on files from elsewhere."""

import re
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import tifffile

from cm2cl.errors import InputError
from cm2cl.io import read_tiff, tiff_stem, write_tiff

OME = "{http://www.openmicroscopy.org/Schemas/OME/2016-06}"


def ome_pixels(path):
    """The OME Pixels element of a file, parsed with ElementTree from the first ImageDescription."""
    with tifffile.TiffFile(path) as tf:
        root = ET.fromstring(tf.pages[0].description)
    pixels = root.find(f"{OME}Image/{OME}Pixels")
    assert pixels is not None
    return pixels


def ome_scale(path):
    """(PhysicalSizeZ, Y, X) in um (None where absent) and the Plane PositionZ list, from OME-XML."""
    px = ome_pixels(path)
    sizes = []
    for ax in "ZYX":
        v = px.get(f"PhysicalSize{ax}")
        if v is not None:
            assert px.get(f"PhysicalSize{ax}Unit") == "µm"
        sizes.append(None if v is None else float(v))
    planes = sorted(px.findall(f"{OME}Plane"), key=lambda p: int(p.get("TheZ")))
    for p in planes:
        assert p.get("PositionZ") is None or p.get("PositionZUnit") == "µm"
    depths = [float(p.get("PositionZ")) for p in planes if p.get("PositionZ") is not None]
    return tuple(sizes), depths


def resolution_um(path):
    """(dy, dx) in um from XResolution / YResolution and ResolutionUnit, as ImageJ's TiffDecoder reads
    them (pixel width = 1 / resolution, in the resolution unit); None when the unit is NONE."""
    with tifffile.TiffFile(path) as tf:
        tags = tf.pages[0].tags
        unit = tags["ResolutionUnit"].value
        (xn, xd), (yn, yd) = tags["XResolution"].value, tags["YResolution"].value
    per = {3: 1e4, 2: 2.54e4}.get(int(unit))
    if per is None:
        return None
    return per * yd / yn, per * xd / xn


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.uint16])
def test_volumes_carry_physical_scale_and_depths_in_ome_and_resolution_tags(tmp_path, dtype):
    rng = np.random.default_rng(0)
    v = (rng.random((3, 5, 7)) * 1000).astype(dtype)
    path = write_tiff(tmp_path / "v.ome.tif", v, voxel_size_um=(250.0, 42.24, 30.5), depths_um=[-250, 0, 250],
                      extra={"kind": "x"})
    sizes, depths = ome_scale(path)
    assert sizes == pytest.approx((250.0, 42.24, 30.5)) and depths == pytest.approx([-250.0, 0.0, 250.0])
    assert resolution_um(path) == pytest.approx((42.24, 30.5), rel=1e-6)
    px = ome_pixels(path)
    assert (px.get("SizeZ"), px.get("SizeY"), px.get("SizeX")) == ("3", "5", "7")
    assert px.get("Type") == {np.float32: "float", np.float64: "double", np.uint16: "uint16"}[dtype]
    with tifffile.TiffFile(path) as tf:           # tifffile: one ZYX series, the array unchanged
        assert tf.is_ome and tf.series[0].axes == "ZYX"
        a = tf.asarray()
    assert a.dtype == np.dtype(dtype) and np.array_equal(a, v)
    a, m = read_tiff(path)
    assert a.dtype == np.dtype(dtype) and np.array_equal(a, v)
    assert m["voxel_size_um"] == pytest.approx((250.0, 42.24, 30.5)) and m["unit"] == "um"
    assert m["depths_um"] == pytest.approx([-250, 0, 250]) and m["extra"] == {"kind": "x"}


def test_an_image_without_known_scale_says_pixels(tmp_path):
    img = np.arange(12, dtype=np.uint16).reshape(3, 4)
    path = write_tiff(tmp_path / "p.ome.tif", img)
    assert ome_scale(path) == ((None, None, None), [])
    assert resolution_um(path) is None
    a, m = read_tiff(path)
    assert np.array_equal(a, img) and m["voxel_size_um"] is None and m["unit"] == "pixel"
    # 2D with a lateral scale: PhysicalSizeX/Y only
    path = write_tiff(tmp_path / "s.ome.tif", img, voxel_size_um=(17.6, 17.6))
    assert ome_scale(path)[0] == (None, pytest.approx(17.6), pytest.approx(17.6))
    assert read_tiff(path)[1]["voxel_size_um"] == pytest.approx((17.6, 17.6))


def test_read_tiff_reads_imagej_and_plain_tiffs_from_elsewhere(tmp_path):
    v = np.random.default_rng(1).random((3, 5, 7)).astype(np.float32)
    # an ImageJ hyperstack (what Fiji saves and what cm2cl wrote before OME): resolution + spacing + unit
    tifffile.imwrite(tmp_path / "ij.tif", v, imagej=True, resolution=(0.5, 0.25),
                     metadata={"spacing": 7.0, "unit": "um", "axes": "ZYX"})
    a, m = read_tiff(tmp_path / "ij.tif")
    assert np.array_equal(a, v) and m["voxel_size_um"] == pytest.approx((7.0, 4.0, 2.0)) and m["unit"] == "um"
    tifffile.imwrite(tmp_path / "ij1.tif", v, imagej=True, resolution=(0.5, 0.5), metadata={"unit": "um", "axes": "ZYX"})
    assert read_tiff(tmp_path / "ij1.tif")[1]["voxel_size_um"] == pytest.approx((1.0, 2.0, 2.0))
    # ImageJ without a unit: pixels, not um
    tifffile.imwrite(tmp_path / "ijpx.tif", v, imagej=True, metadata={"axes": "ZYX"})
    assert read_tiff(tmp_path / "ijpx.tif")[1]["unit"] == "pixel"
    # a plain TIFF with resolution in cm (e.g. from a camera program)
    tifffile.imwrite(tmp_path / "cm.tif", v[0], resolution=(1e4 / 3.0, 1e4 / 2.0), resolutionunit="CENTIMETER")
    assert read_tiff(tmp_path / "cm.tif")[1]["voxel_size_um"] == pytest.approx((2.0, 3.0))
    # a plain TIFF without scale (e.g. a DiffuserCam PSF)
    tifffile.imwrite(tmp_path / "plain.tif", v, photometric="minisblack")
    a, m = read_tiff(tmp_path / "plain.tif")
    assert a.shape == v.shape and m["voxel_size_um"] is None and m["unit"] == "pixel" and m["depths_um"] is None


def test_bad_geometry_and_files_are_one_line_input_errors(tmp_path):
    v = np.zeros((3, 4, 5), np.float32)
    cases = [
        (dict(voxel_size_um=(1.0, 2.0)), "voxel_size_um must be (dz, dy, dx) for a 3D array"),
        (dict(voxel_size_um=(1.0, -2.0, 2.0)), "voxel sizes must be positive"),
        (dict(voxel_size_um=(1.0, "a", 2.0)), "voxel_size_um must be numbers"),
        (dict(voxel_size_um=(1.0, 2.0, 2.0), depths_um=[0, 1]), "2 depths for 3 planes"),
    ]
    for kw, msg in cases:
        with pytest.raises(InputError, match=re.escape(msg)) as info:
            write_tiff(tmp_path / "x.ome.tif", v, **kw)
        assert "\n" not in str(info.value) and "x.ome.tif" in str(info.value)
    with pytest.raises(InputError, match="non-empty 2D or 3D"):
        write_tiff(tmp_path / "x.ome.tif", np.zeros(4))
    assert not (tmp_path / "x.ome.tif").exists()
    with pytest.raises(InputError, match="no such file"):
        read_tiff(tmp_path / "missing.tif")
    (tmp_path / "bad.tif").write_text("not a tiff")
    with pytest.raises(InputError, match="not a readable TIFF"):
        read_tiff(tmp_path / "bad.tif")


@pytest.mark.parametrize("old, new, msg", [
    ('PhysicalSizeX="2.0"', 'PhysicalSizeX="abc"', "PhysicalSizeX is 'abc', not a number"),
    ('PhysicalSizeZ="10.0"', 'PhysicalSizeZ="inf"', "PhysicalSizeZ is 'inf', not a finite number"),
    ('PositionZ="0.0"', 'PositionZ="deep"', "Plane PositionZ is 'deep', not a number"),
    ('TheZ="1"', 'TheZ="1.5"', "Plane TheZ is '1.5', not an integer"),
    ('TheZ="1"', 'TheZ="x"', "Plane TheZ is 'x', not a number"),
    ('&quot;shape&quot;: [3, 4, 5]', '&quot;shape&quot;: &quot;345&quot;', "has shape '345', not a list of positive integers"),
    ('&quot;shape&quot;: [3, 4, 5]', '&quot;shape&quot;: [3, 4, true]', "not a list of positive integers")])
def test_ome_metadata_of_the_wrong_type_is_a_one_line_error(tmp_path, old, new, msg):
    """OME-XML whose lengths, positions, plane indices or recorded shape are not numbers (issue 27: they
    were tracebacks) is refused with one line naming the file and the value."""
    from cm2cl.io.tiff import tiff_depths

    p = tmp_path / "v.ome.tif"
    write_tiff(p, np.ones((3, 4, 5), np.float32), voxel_size_um=(10.0, 2.0, 2.0), depths_um=[0.0, 10.0, 20.0])
    with tifffile.TiffFile(p) as tf:
        xml = tf.pages[0].description
    assert old in xml, xml[:2000]
    tifffile.tiffcomment(p, xml.replace(old, new, 1).encode("utf-8"))
    for read in (read_tiff,) if "shape" in old else (read_tiff, tiff_depths):   # depths need no shape
        with pytest.raises(InputError) as info:
            read(p)
        assert msg in str(info.value) and "v.ome.tif" in str(info.value) and "\n" not in str(info.value)


def test_a_plane_index_too_long_for_a_machine_integer_leaves_the_depths_unknown(tmp_path):
    """Issue 27 F6: TheZ = 10^22 was a TypeError; it is read exactly and, as any TheZ that does not number
    the planes 0..n-1, leaves the depths unknown (the voxel sizes still read)."""
    p = tmp_path / "v.ome.tif"
    write_tiff(p, np.ones((3, 4, 5), np.float32), voxel_size_um=(10.0, 2.0, 2.0), depths_um=[0.0, 10.0, 20.0])
    with tifffile.TiffFile(p) as tf:
        xml = tf.pages[0].description
    tifffile.tiffcomment(p, xml.replace('TheZ="1"', 'TheZ="99999999999999999999999"', 1).encode("utf-8"))
    _, m = read_tiff(p)
    assert m["depths_um"] is None and m["voxel_size_um"] == pytest.approx((10.0, 2.0, 2.0))


@pytest.mark.parametrize("record, msg", [
    ({"voxel_size_um": "abc"}, "voxel_size_um must be numbers (dz, dy, dx), got 'abc'"),
    ({"voxel_size_um": [1, "x", 2]}, "voxel_size_um must be numbers (dz, dy, dx), got [1, 'x', 2]"),
    ({"voxel_size_um": 5}, "voxel_size_um must be numbers (dz, dy, dx), got 5"),
    ({"voxel_size_um": [1, 2]}, "voxel_size_um must be (dz, dy, dx) for a 3D array"),
    ({"voxel_size_um": [10, -2, 2]}, "voxel sizes must be positive and finite"),
    ({"voxel_size_um": [10, 2, 2], "depths_um": "abc"}, "depths_um must be numbers, got 'abc'"),
    ({"voxel_size_um": [10, 2, 2], "depths_um": [0, 1]}, "2 depths for 3 planes"),
    ({"extra": [1, 2]}, "has extra list, not a mapping")])
def test_a_legacy_record_of_the_wrong_type_is_a_one_line_error(tmp_path, record, msg):
    """Issue 27 F7: a plain TIFF whose cm2cl record (what cm2cl < 0.2 wrote in the ImageDescription) holds
    voxel sizes, depths or extra of the wrong type was a traceback; it is one line naming the file."""
    import json

    p = tmp_path / "legacy.tif"
    tifffile.imwrite(p, np.ones((3, 4, 5), np.float32), description=json.dumps({"cm2cl": "0.1", **record}),
                     photometric="minisblack")
    with pytest.raises(InputError) as info:
        read_tiff(p)
    assert msg in str(info.value) and "legacy.tif': its cm2cl record" in str(info.value)
    assert "\n" not in str(info.value)
    tifffile.imwrite(p, np.ones((3, 4, 5), np.float32), description=json.dumps(
        {"cm2cl": "0.1", "voxel_size_um": [10, 2, 2], "depths_um": [0, 10, 20], "extra": {"k": 1}}),
        photometric="minisblack")
    _, m = read_tiff(p)                                 # a good one still reads
    assert m["voxel_size_um"] == (10.0, 2.0, 2.0) and m["depths_um"] == [0.0, 10.0, 20.0] and m["extra"] == {"k": 1}


def test_ome_image_and_channel_are_named(rt, tmp_path):
    """Issue 26: viewers show the OME Image's name and the channel (they showed Image0 and nothing): the
    file's stem by default, the reconstruction's output and measurement, the channel and its emission."""
    import numpy as np

    from cm2cl.cli import main
    from test_admm import bead_problem

    def image_and_channel(p):
        root = ET.fromstring(tifffile.TiffFile(p).ome_metadata)
        ns = {"o": root.tag[1:].split("}")[0]}
        img = root.find("o:Image", ns)
        return img.get("Name"), img.find("o:Pixels/o:Channel", ns).attrib

    write_tiff(tmp_path / "plain.ome.tif", np.ones((4, 5), np.float32))
    name, ch = image_and_channel(tmp_path / "plain.ome.tif")
    assert name == "plain" and "Name" not in ch and "EmissionWavelength" not in ch
    write_tiff(tmp_path / "c.ome.tif", np.ones((4, 5), np.float32), name="cells", channel="GFP", emission_nm=510)
    name, ch = image_and_channel(tmp_path / "c.ome.tif")
    assert name == "cells" and ch["Name"] == "GFP" and float(ch["EmissionWavelength"]) == 510.0
    assert ch["EmissionWavelengthUnit"] == "nm"
    with pytest.raises(InputError, match="emission wavelength"):
        write_tiff(tmp_path / "d.ome.tif", np.ones((4, 5), np.float32), emission_nm=-3)
    psf, _, y = bead_problem(6)
    tifffile.imwrite(tmp_path / "psf.tif", psf.astype(np.float32), photometric="minisblack")
    tifffile.imwrite(tmp_path / "frame7.tif", (y * 1000).astype(np.float32))
    assert main(["reconstruct", str(tmp_path / "frame7.tif"), "--psf", str(tmp_path / "psf.tif"), "-o",
                 str(tmp_path / "vol.ome.tif"), "--max-iter", "3", "--quiet", "--channel", "GCaMP6f",
                 "--emission-nm", "512"]) == 0
    name, ch = image_and_channel(tmp_path / "vol.ome.tif")
    assert name == "vol (cm2cl reconstruction of frame7.tif)" and ch["Name"] == "GCaMP6f"
    assert float(ch["EmissionWavelength"]) == 512.0


def test_tiff_stem():
    assert str(tiff_stem("a/vol.ome.tif")) == "a/vol" and str(tiff_stem("vol.TIFF")) == "vol"
    assert str(tiff_stem("v.1.tif")) == "v.1"
