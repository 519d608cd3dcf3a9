"""The natural waters' locus (core/model/jerlov.py): the channels' attenuation through a camera's
bands, the locus placed by the channels a survey pins, and the free channels filled from it."""
import numpy as np
import pytest
import torch

from recgs_addon.core.model import jerlov
from recgs_addon.core.model.medium import Medium


def test_a_spectrally_flat_water_attenuates_every_channel_alike():
    flat = np.full(len(jerlov.WAVELENGTHS), 0.3)
    assert np.allclose(jerlov.band_attenuation(flat, 4.0), 0.3, rtol=1e-12)


def test_a_short_path_sees_the_band_weighted_mean_and_a_long_one_the_clearest_part():
    """Over a vanishing path a channel's attenuation is its band's sensitivity-weighted mean
    (the first term of the expansion, computed here in float64 independently); over a longer
    one it falls towards the band's least-attenuated wavelengths."""
    row = jerlov.KD[jerlov.TYPES.index("3C")]
    lam = np.arange(400.0, 700.1, 5.0)
    k = np.interp(lam, jerlov.WAVELENGTHS, row)
    for c, (centre, width) in enumerate(jerlov.CHANNELS_NM):
        s = np.exp(-0.5 * ((lam - centre) / width) ** 2)
        mean = float((s * k).sum() / s.sum())
        assert jerlov.band_attenuation(row, 1e-6)[c] == pytest.approx(mean, rel=1e-5)
    a1, a6 = jerlov.band_attenuation(row, 1.0), jerlov.band_attenuation(row, 6.0)
    assert np.all(a6 < a1)


def test_the_locus_takes_red_first_and_leaves_blue_clearest_offshore_green_inshore():
    loc = jerlov.locus()
    oceanic = [jerlov.TYPES.index(t) for t in ("I", "IA", "IB", "II")]
    coastal = [jerlov.TYPES.index(t) for t in ("1C", "3C", "5C", "7C", "9C")]
    assert np.all(loc[:-1, 0] > loc[:-1, 1])                 # red above green but in the murkiest
    assert np.all(loc[oceanic, 2] < loc[oceanic, 1])         # open ocean: blue the clearest
    assert np.all(loc[coastal, 1] < loc[coastal, 2])         # coast: green the clearest
    assert np.all(np.diff(loc[:, 1]) > 0) and np.all(np.diff(loc[:, 2]) > 0)   # murkier down the list


@pytest.mark.parametrize("name, scale", [("IB", 1.0), ("1C", 2.5), ("5C", 0.4)])
def test_two_pinned_channels_place_the_locus_in_any_units_and_give_the_third(name, scale):
    true = jerlov.locus()[jerlov.TYPES.index(name)] * scale   # the survey's units: scale per metre
    for free in range(3):
        pinned = [c != free for c in range(3)]
        att = true.copy()
        att[free] = -0.01                                    # whatever the photos made of it
        sd = np.where(pinned, 0.01 * true, np.inf)
        got = jerlov.fill(att, sd, pinned)
        assert got["source"][free] == "prior"
        assert got["values"][free] == pytest.approx(true[free], rel=0.12), (free, got)
        for c in range(3):
            if c != free:
                assert got["values"][c] == att[c]
        assert 0 < got["values_spread"][free] < got["values"][free]   # finite: the locus is narrow


def test_one_pinned_channel_places_the_locus_only_in_metres():
    true = jerlov.locus()[jerlov.TYPES.index("3C")]
    sd = np.array([0.005, np.inf, np.inf])
    assert jerlov.fill(true, sd, [True, False, False]) is None
    got = jerlov.fill(true, sd, [True, False, False], metres=True)
    assert got is not None and got["source"] == ["photos", "prior", "prior"]
    assert got["scale"] == 1.0


def test_a_loose_channel_moves_towards_the_locus_by_the_weight_of_each():
    true = jerlov.locus()[jerlov.TYPES.index("1C")]
    att = true * np.array([1.0, 1.6, 1.0])                   # green read 60 % high ...
    tight = jerlov.fill(att, [0.005, 0.05 * att[1], 0.005], [True, False, True])
    loose = jerlov.fill(att, [0.005, 0.5 * att[1], 0.005], [True, False, True])
    assert tight["source"][1] == loose["source"][1] == "photos and prior"
    # ... a well-measured green stays near the photos' value, a poorly measured one nears the locus
    assert abs(tight["values"][1] - att[1]) < abs(loose["values"][1] - att[1])
    assert true[1] < loose["values"][1] < att[1]
    assert loose["values_spread"][1] < 0.5 * att[1]


def test_the_pinned_channels_misfit_says_how_unlike_a_natural_water_they_are():
    near = jerlov.locus()[jerlov.TYPES.index("II")]
    far = near * np.array([1.0, 4.0, 0.25])                   # green murky, blue clearer than any water
    sd = np.full(3, 1e-3)
    assert jerlov.place(near, sd, [True] * 3)["misfit"] < 0.5
    assert jerlov.place(far, sd, [True] * 3)["misfit"] > 3.0


def test_the_water_setup_starts_a_free_channel_from_the_locus_and_says_so():
    from types import SimpleNamespace

    from recgs_addon.core.train.water import MediumMixin

    true = jerlov.locus()[jerlov.TYPES.index("3C")]
    start = Medium.from_values({"attenuation": [true[0], 0.9, true[2]], "backscatter": [0.3] * 3,
                                "veil": [0.05, 0.1, 0.1], "length": 3.0})
    fit = {"fit": {"attenuation": [true[0], 0.9, true[2]]},
           "spread": {"attenuation": [0.004, 5.0, 0.004]}, "medium": start}
    host = SimpleNamespace(medium_info={})
    MediumMixin._natural_prior(host, fit, {"attenuation": ["pinned", "free", "pinned"]})
    info = host.medium_info["prior"]
    assert info["source"] == ["photos", "prior", "photos"]
    vals = fit["medium"].values()
    assert vals["attenuation"][1] == pytest.approx(true[1], rel=0.12)
    assert vals["attenuation"][0] == pytest.approx(true[0], rel=1e-4)
    assert vals["backscatter"] == pytest.approx(start.values()["backscatter"], rel=1e-5)
    assert isinstance(fit["medium"].raw, torch.nn.Parameter)


def test_the_report_names_the_type_and_each_filled_channels_source():
    from recgs_addon.core.outputs.report import _water_section

    medium = {"coefficients": {"attenuation": [0.5, 0.23, 0.34], "backscatter": [0.3] * 3, "veil": [0.02, 0.08, 0.06]},
              "reason": "the sparse points show water",
              "prior": {"name": "1C", "type": 5.0, "misfit": 0.1, "source": ["photos", "prior", "photos"],
                        "values": [0.5, 0.231, 0.34], "values_spread": [0.01, 0.061, 0.01]}}
    text = "\n".join(_water_section(medium))
    assert "Jerlov's water type 1C" in text and "green 0.231 +- 0.061 (prior)" in text
    assert "red 0.500" not in text                     # a channel the photos pin is not listed as filled
    medium["prior"]["source"] = ["photos"] * 3
    assert "training starts it from there" not in "\n".join(_water_section(medium))
    medium["prior"] = {"reason": "fewer than two channels pinned: the locus is not placed"}
    assert "Jerlov" not in "\n".join(_water_section(medium))
    # the channels whose backscatter rate one altitude left free and the fit tied to the attenuation
    medium["rate_tied"] = [False, True, True]
    assert "backscatter rate of green, blue free" in "\n".join(_water_section(medium))
    medium["rate_tied"] = [False] * 3
    assert "backscatter rate of" not in "\n".join(_water_section(medium))
