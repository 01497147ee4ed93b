"""mtcw_core.scene: scene_variant and validation errors that name the field."""

from __future__ import annotations

import pytest

from mtcw_core.scene import Scene, SceneError, scene_from_dict, scene_variant

from .conftest import make_scene


class TestSceneVariant:
    def test_nested_mapping_merges(self):
        sc = make_scene()
        v = scene_variant(sc, digitizer={"samples": 2**12})
        assert isinstance(v, Scene)
        assert v.digitizer.samples == 2**12
        assert v.digitizer.sample_rate_hz == sc.digitizer.sample_rate_hz  # kept
        assert v.laser == sc.laser and v.targets == sc.targets
        assert sc.digitizer.samples == 2**14  # the original is untouched

    def test_list_of_mappings_merges_item_by_item(self):
        sc = make_scene(targets=[{"range_m": 1.0, "loss_db": 20.0}, {"range_m": 2.0, "loss_db": 30.0}])
        v = scene_variant(sc, targets=[{"loss_db": 60.0}])
        assert [t.loss_db for t in v.targets] == [60.0, 30.0]
        assert [t.range_m for t in v.targets] == [1.0, 2.0]

    def test_extra_list_items_appended(self):
        sc = make_scene()
        v = scene_variant(sc, targets=[{}, {"range_m": 5.0, "velocity_mps": 1.0}])
        assert len(v.targets) == 2
        assert v.targets[1].range_m == 5.0 and v.targets[1].loss_db == 20.0  # model default

    def test_deep_nesting(self):
        sc = make_scene()
        v = scene_variant(sc, modulator={"tones": [{"modulation_index": 0.2}]})
        assert v.modulator.tones[0].modulation_index == 0.2
        assert v.modulator.tones[0].frequency_hz == 500e6
        assert v.modulator.tones_hz == sc.modulator.tones_hz

    def test_optional_section_set_and_cleared(self):
        sc = make_scene()
        v = scene_variant(sc, pulsing={"period_s": 1e-6, "duty": 0.5})
        assert v.pulsing.period_s == 1e-6 and v.pulsing.reference_channel is True
        assert scene_variant(v, pulsing=None).pulsing is None

    def test_scalar_replaces(self):
        assert scene_variant(make_scene(), name="other", lo_fraction=0.3).lo_fraction == 0.3

    def test_no_changes_is_equal(self):
        sc = make_scene()
        assert scene_variant(sc) == sc

    def test_invalid_change_names_the_field(self):
        with pytest.raises(SceneError, match=r"targets\.0\.loss_db"):
            scene_variant(make_scene(), targets=[{"loss_db": -1.0}])

    def test_unknown_field_named(self):
        with pytest.raises(SceneError, match=r"digitizer\.bogus_hz"):
            scene_variant(make_scene(), digitizer={"bogus_hz": 1.0})

    def test_tone_above_nyquist_named(self):
        with pytest.raises(SceneError, match=r"modulator\.tones\.2\.frequency_hz"):
            scene_variant(make_scene(), digitizer={"sample_rate_hz": 1.5e9})

    def test_error_names_the_variant(self):
        with pytest.raises(SceneError, match="variant of test"):
            scene_variant(make_scene(), laser={"wavelength_m": 0.0})

    def test_scene_error_is_a_value_error(self):
        with pytest.raises(ValueError):
            scene_variant(make_scene(), lo_fraction=1.5)

    def test_empty_list_is_not_silently_ignored(self):
        with pytest.raises(SceneError, match="targets"):
            scene_variant(make_scene(), targets=[])


class TestSceneValidation:
    BASE = {"modulator": {"tones": [{"frequency_hz": 5e8}, {"frequency_hz": 7e8}]}, "targets": [{"range_m": 1.0}]}

    def test_a_target_behind_the_calibration_zero_is_simulated_while_its_echo_leaves_first(self):
        """tau0 = 3.1 ns: a range of -0.4 m is a delay of 0.43 ns, light still arriving after it left;
        at -0.5 m (-0.24 ns) the simulator refuses the frame, naming the target."""
        from mtcw_core.simulate import Simulator

        base = {**self.BASE, "digitizer": {"samples": 1024}, "paths": {"tau0_s": 3.1e-9}}
        assert Simulator(scene_from_dict({**base, "targets": [{"range_m": -0.4}]})).next_frame().n == 1024
        behind = Simulator(scene_from_dict({**base, "targets": [{"range_m": -0.5}]}))
        with pytest.raises(SceneError, match=r"targets\.0\.range_m: .* by frame 0"):
            behind.next_frame()

    def test_minimal_scene_defaults(self):
        sc = scene_from_dict(self.BASE)
        assert sc.tones_hz == [5e8, 7e8] and sc.pulsing is None

    @pytest.mark.parametrize("change,field", [
        ({"targets": []}, "targets"),
        ({"targets": [{"range_m": 1.0, "loss_db": -3}]}, "targets.0.loss_db"),
        ({"laser": {"linewidth_hz": -1}}, "laser.linewidth_hz"),
        ({"digitizer": {"samples": 10}}, "digitizer.samples"),
        ({"digitizer": {"adc_bits": 20}}, "digitizer.adc_bits"),
        ({"modulator": {"tones": [{"frequency_hz": 5e8}, {"frequency_hz": 5e8}]}}, "modulator"),
        ({"modulator": {"tones": [{"frequency_hz": 5e8, "modulation_index": 4.0}]}},
         "modulator.tones.0.modulation_index"),
        ({"pulsing": {"period_s": 1e-6, "duty": 1.5}}, "pulsing.duty"),
        ({"receiver": {"kind": "quantum"}}, "receiver.kind"),
        ({"mystery": 1}, "mystery"),
        # no light arrives before it left: an LO path shorter than nothing
        ({"paths": {"lo_path_difference_m": -1.0}}, "paths: Value error, lo_path_difference_m"),
    ])
    def test_error_names_the_field(self, change, field):
        with pytest.raises(SceneError) as e:
            scene_from_dict({**self.BASE, **change})
        assert field in str(e.value)

    def test_missing_required_named(self):
        with pytest.raises(SceneError, match="modulator"):
            scene_from_dict({"targets": [{"range_m": 1.0}]})

    def test_frozen(self):
        sc = scene_from_dict(self.BASE)
        with pytest.raises(Exception):
            sc.seed = 3
