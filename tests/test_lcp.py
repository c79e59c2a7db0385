"""Adobe lens profiles (LCP) as vigproc profiles (vigproc.stores.lcp).

The LCP files here are synthetic: Adobe's own profiles are not redistributable, and no
LCP file under a licence that allows copying it into this repository was found.  They
follow the two layouts real files use (attributes of rdf:Description elements, and child
elements under rdf:parseType="Resource" with the identity given once), with values of
the size real profiles have (a Canon EF 35mm f/1.4L USM on a 5D Mark II: FocalLengthX
0.93, centre (0.503, 0.488), vignette -1.68, -0.30, 1.19 at f/1.6).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from vigproc.stores.lcp import LcpError, import_lcp, lens_id_for, read_lcp

HEAD = ('<?xml version="1.0" encoding="UTF-8"?>\n<x:xmpmeta xmlns:x="adobe:ns:meta/">\n'
        ' <rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">\n'
        '  <rdf:Description rdf:about="" xmlns:photoshop="http://ns.adobe.com/photoshop/1.0/"\n'
        '    xmlns:stCamera="http://ns.adobe.com/photoshop/1.0/camera-profile">\n'
        '   <photoshop:CameraProfiles>\n    <rdf:Seq>\n')
TAIL = '    </rdf:Seq>\n   </photoshop:CameraProfiles>\n  </rdf:Description>\n </rdf:RDF>\n</x:xmpmeta>\n'
IDENTITY = dict(Author="Adobe Systems, Inc.", Make="Canon", Model="Canon EOS 5D Mark II",
                UniqueCameraModel="Canon EOS 5D Mark II", CameraRawProfile="True", Lens="EF35mm f/1.4L USM",
                LensPrettyName="Canon EF 35mm f/1.4L USM", SensorFormatFactor="1", ImageWidth="5634",
                ImageLength="3753")
VIG = (-1.676514, -0.297444, 1.187675)


def av(n: float) -> str:
    return f"{2 * math.log2(n):.6f}"  # APEX aperture value


def entry_attrs(focal=35, n=1.6, dist=3.0, vig=VIG, identity=IDENTITY, persp=None, vig_geo=None) -> str:
    """One entry in the attribute layout (files since 2010)."""
    ident = " ".join(f'stCamera:{k}="{v}"' for k, v in identity.items())
    persp = persp if persp is not None else dict(FocalLengthX="0.932995", FocalLengthY="0.932995",
                                                 ImageXCenter="0.502747", ImageYCenter="0.488436")
    p = " ".join(f'stCamera:{k}="{v}"' for k, v in persp.items())
    vg = " ".join(f'stCamera:{k}="{v}"' for k, v in (vig_geo or {}).items())
    params = " ".join(f'stCamera:VignetteModelParam{i + 1}="{a}"' for i, a in enumerate(vig))
    return (f'     <rdf:li>\n      <rdf:Description {ident} stCamera:FocalLength="{focal}" '
            f'stCamera:FocusDistance="{dist}" stCamera:ApertureValue="{av(n)}">\n'
            f'       <stCamera:PerspectiveModel>\n        <rdf:Description stCamera:Version="2" {p} '
            f'stCamera:RadialDistortParam1="-0.1">\n'
            f'         <stCamera:VignetteModel>\n          <rdf:Description {vg} {params} '
            f'stCamera:ResidualMeanError="0.0015"/>\n         </stCamera:VignetteModel>\n'
            f'        </rdf:Description>\n       </stCamera:PerspectiveModel>\n      </rdf:Description>\n'
            f'     </rdf:li>\n')


def entry_elements(focal=35, n=1.6, dist=3.0, vig=VIG, identity=None) -> str:
    """One entry in the element layout (older files), identity only where given."""
    ident = "".join(f"<stCamera:{k}>{v}</stCamera:{k}>" for k, v in (identity or {}).items())
    params = "".join(f"<stCamera:VignetteModelParam{i + 1}>{a}</stCamera:VignetteModelParam{i + 1}>"
                     for i, a in enumerate(vig))
    return (f'     <rdf:li rdf:parseType="Resource">{ident}<stCamera:FocalLength>{focal}</stCamera:FocalLength>'
            f'<stCamera:FocusDistance>{dist}</stCamera:FocusDistance>'
            f'<stCamera:ApertureValue>{av(n)}</stCamera:ApertureValue>'
            f'<stCamera:PerspectiveModel rdf:parseType="Resource"><stCamera:Version>2</stCamera:Version>'
            f'<stCamera:FocalLengthX>0.932995</stCamera:FocalLengthX>'
            f'<stCamera:FocalLengthY>0.932995</stCamera:FocalLengthY>'
            f'<stCamera:VignetteModel rdf:parseType="Resource">{params}</stCamera:VignetteModel>'
            f'</stCamera:PerspectiveModel></rdf:li>\n')


def write(path: Path, *entries: str) -> Path:
    path.write_text(HEAD + "".join(entries) + TAIL, encoding="utf-8")
    return path


def lum(e, w: int, h: int) -> np.ndarray:
    return np.exp(e.log_phi_at((np.arange(h) + 0.5) / h, (np.arange(w) + 0.5) / w, w, h))


def test_reads_the_attribute_layout(tmp_path: Path) -> None:
    f = write(tmp_path / "Canon (EF35mm f1.4L USM) - RAW.lcp", entry_attrs(), entry_attrs(n=4.0, vig=(-0.6, 0.2, -0.1)))
    entries, skipped = read_lcp(f)
    assert len(entries) == 2 and skipped == []
    e = entries[0]
    assert (e.make, e.model, e.lens) == ("Canon", "Canon EOS 5D Mark II", "EF35mm f/1.4L USM")
    assert e.raw and e.focal_mm == 35 and e.fnumber == pytest.approx(1.6) and e.distance_m == 3.0
    assert e.alpha == VIG and (e.cx, e.cy) == (0.502747, 0.488436) and e.image_size == (5634, 3753)
    # the model at a corner, by hand: r = distance / (FocalLengthX * max(W, H))
    w, h = 600, 400
    x, y = (0.5 / w - 0.502747) * w, (0.5 / h - 0.488436) * h
    r2 = (x * x + y * y) / (0.932995 * w) ** 2
    assert lum(e, w, h)[0, 0] == pytest.approx(1 + VIG[0] * r2 + VIG[1] * r2**2 + VIG[2] * r2**3)
    assert lum(e, w, h).min() < 0.5  # ~1.2 EV in the corners at f/1.6


def test_reads_the_element_layout_with_identity_once(tmp_path: Path) -> None:
    f = write(tmp_path / "old.lcp", entry_elements(identity=IDENTITY), entry_elements(focal=50, n=2.8))
    entries, _ = read_lcp(f)
    assert [e.focal_mm for e in entries] == [35, 50]
    assert entries[1].lens == "EF35mm f/1.4L USM" and entries[1].model == "Canon EOS 5D Mark II"
    assert entries[1].fnumber == pytest.approx(2.8)
    assert (entries[0].cx, entries[0].cy) == (0.5, 0.5)  # no centre given: the middle


def test_import_keys_like_exif_and_states_the_fit_error(tmp_path: Path) -> None:
    f = write(tmp_path / "a.lcp", entry_attrs(), entry_attrs(dist=0.3, vig=(-3.0, 1.0, 0.0)),
              entry_attrs(n=4.0, vig=(-0.6, 0.2, -0.1)))
    imports, skipped = import_lcp([f])
    assert len(imports) == 2 and skipped == []
    keys = sorted(str(i.profile.key) for i in imports)
    assert keys == ["canon|canon eos 5d mark ii|ef35mm f/1.4l usm @ f=33.4mm N=1.6 3:2",
                    "canon|canon eos 5d mark ii|ef35mm f/1.4l usm @ f=33.4mm N=4.0 3:2"]
    wide = next(i for i in imports if i.profile.key.aperture_bin == "N=1.6")
    # of the two distances at f/1.6, the farther one (3 m) is the profile; the 0.3 m one is named
    assert wide.entry.distance_m == 3.0 and [e.distance_m for e in wide.superseded] == [0.3]
    for i in imports:
        assert i.rms_ev <= 0.01 and i.max_ev < 0.1, i.to_dict()
        assert i.profile.trusted and i.profile.provenance == "user" and "Adobe LCP" in i.profile.notes
        assert f"{i.rms_ev:.2e} EV RMS" in i.profile.notes
        # the stored profile gives back the LCP's field (within the stated error), at any resolution
        m = i.profile.model(900, 600)
        d = (m.log_field() - np.log(lum(i.entry, 900, 600))) / math.log(2)
        assert float(np.sqrt(np.mean(d * d))) == pytest.approx(i.rms_ev, abs=2e-3)
    assert wide.falloff_ev > 0.4


def test_a_frame_with_that_exif_finds_the_imported_profile(tmp_path: Path) -> None:
    from vigproc.io.exif import LensKey
    from vigproc.stores.profiles import ProfileStore

    imports, _ = import_lcp([write(tmp_path / "a.lcp", entry_attrs())])
    with ProfileStore(tmp_path / "p.sqlite") as store:
        store.put(imports[0].profile)
        key = LensKey(make="canon", model="canon eos 5d mark ii", lens="ef35mm f/1.4l usm", focal_mm=35.0,
                      fnumber=1.6)
        hit = store.lookup(key, 6000, 4000, trusted_only=True)
    assert hit is not None and hit.key == imports[0].profile.key


def test_make_only_profiles_and_unusable_lens_names(tmp_path: Path) -> None:
    ident = dict(Make="PENTAX", Lens="Sigma Lens", LensPrettyName="SIGMA 18-50mm F2.8-4.5 DC OS HSM",
                 CameraRawProfile="True", SensorFormatFactor="1.5")
    f = write(tmp_path / "pentax.lcp", entry_attrs(focal=18, n=4.5, identity=ident, persp={}))
    (e,), _ = read_lcp(f)
    # "Sigma Lens" names no lens: Adobe's pretty name keys it; no camera model: "?"
    assert lens_id_for(e) == "pentax|?|sigma 18-50mm f2.8-4.5 dc os hsm"
    assert lens_id_for(e, camera_model="PENTAX K-5") == "pentax|pentax k-5|sigma 18-50mm f2.8-4.5 dc os hsm"
    # no FocalLengthX: the 35-mm equivalent focal length over a 36 mm long side
    assert e.focal_lengths_px(3000, 2000) == pytest.approx((18 * 1.5 / 36 * 3000,) * 2)
    imports, _ = import_lcp([f], camera_model="PENTAX K-5")
    assert imports[0].profile.key.lens_id.startswith("pentax|pentax k-5|")
    imports, _ = import_lcp([f], lens_id="Pentax|PENTAX K-5|smc DA 18-55")
    assert imports[0].profile.key.lens_id == "pentax|pentax k-5|smc da 18-55"


def test_raw_profiles_win_over_jpeg_ones(tmp_path: Path) -> None:
    jpeg = dict(IDENTITY, CameraRawProfile="False")
    f = write(tmp_path / "both.lcp", entry_attrs(identity=jpeg, vig=(-0.2, 0, 0)), entry_attrs())
    (imp,), _ = import_lcp([f])
    assert imp.entry.raw and imp.entry.alpha == VIG and imp.superseded == []
    (imp,), _ = import_lcp([f], include_jpeg=True)
    assert imp.entry.raw and len(imp.superseded) == 1


def test_entries_without_vignetting_are_reported(tmp_path: Path) -> None:
    no_vig = entry_attrs().replace('<stCamera:VignetteModel>\n          <rdf:Description', '<stCamera:X>\n <rdf:Description').replace(
        '</stCamera:VignetteModel>', '</stCamera:X>')
    fisheye = entry_attrs().replace("PerspectiveModel", "FisheyeModel")
    entries, skipped = read_lcp(write(tmp_path / "f.lcp", no_vig, fisheye, entry_attrs()))
    assert len(entries) == 1 and len(skipped) == 2
    assert "no VignetteModel" in skipped[0] and "fisheye" in skipped[1]


@pytest.mark.parametrize("text, match", [
    ('<?xml version="1.0"?><!DOCTYPE x [<!ENTITY a "aaaa">]><x>&a;</x>', "DTD or entity"),
    ("not xml at all <", "not an XML lens profile"),
    ("<x:xmpmeta xmlns:x='adobe:ns:meta/'/>", "no photoshop:CameraProfiles"),
    (HEAD + entry_attrs(vig=("nan", 0, 0)) + TAIL, "VignetteModelParam1"),
    (HEAD + entry_attrs(focal="1e400") + TAIL, "FocalLength"),
    (HEAD + entry_attrs(focal="thirty") + TAIL, "not a number"),
])
def test_hostile_files_are_typed_errors_naming_the_file(tmp_path: Path, text: str, match: str) -> None:
    f = tmp_path / "bad\nname.lcp"
    f.write_text(text, encoding="utf-8")
    with pytest.raises(LcpError, match=match) as exc:
        read_lcp(f)
    assert "bad\\nname.lcp" in str(exc.value) and "\n" not in str(exc.value)


def test_a_vignette_that_blacks_out_the_frame_is_skipped(tmp_path: Path) -> None:
    f = write(tmp_path / "dark.lcp", entry_attrs(vig=(-5.0, 0.0, 0.0)), entry_attrs(n=4.0))
    imports, skipped = import_lcp([f])
    assert len(imports) == 1 and len(skipped) == 1 and "falls to" in skipped[0]


def test_cli_import_lcp(tmp_path: Path, capsys) -> None:
    from vigproc.frontends.cli import main

    f = write(tmp_path / "a.lcp", entry_attrs(), entry_attrs(n=4.0, vig=(-0.6, 0.2, -0.1)))
    db = tmp_path / "p.sqlite"
    assert main(["profile", "--profile-db", str(db), "import-lcp", str(f), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert len(out["imported"]) == 2 and all(i["fit_rms_ev"] <= 0.01 for i in out["imported"])
    assert main(["profile", "--profile-db", str(db), "list"]) == 0
    listing = capsys.readouterr().out
    assert listing.count("ef35mm f/1.4l usm") == 2
    # a dry run stores nothing; a bad file fails with the profile exit code, naming it
    assert main(["profile", "--profile-db", str(tmp_path / "q.sqlite"), "import-lcp", str(f), "--dry-run"]) == 0
    assert "2 profiles" in capsys.readouterr().out
    bad = tmp_path / "bad.lcp"
    bad.write_text("<x/>")
    assert main(["profile", "--profile-db", str(db), "import-lcp", str(bad)]) == 6
    assert "bad.lcp" in capsys.readouterr().err
