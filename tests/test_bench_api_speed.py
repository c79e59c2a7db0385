"""bench speed --api: vigproc.estimate and a peer timed on the same frames, interleaved."""

import numpy as np

from benchmarks.api_speed import CASES, api_speed


def test_api_speed_times_every_case_and_the_peers_floor():
    rng = np.random.default_rng(0)
    bases = [0.3 + 0.4 * rng.random((320, 480, 3)) for _ in range(2)]
    seen, timed = [], []

    def peer(lum, _field=None):
        seen.append(lum.shape)

    def estimate(img):
        import vigproc

        timed.append(img.shape)
        return vigproc.estimate(img)

    r = api_speed(bases, peer, rounds=2, estimate=estimate)
    assert [c.case for c in r.cases] == list(CASES)
    # the warm-up, then every base x case in each round; the peer on its luminance, and its floor each round
    assert len(timed) == 1 + 2 * 2 * len(CASES) and all(s == (320, 480, 3) for s in timed)
    assert seen.count((320, 480)) == 2 * 2 * len(CASES) and seen.count((16, 16)) == 1 + 2 * 2
    for c in r.cases:
        assert c.n == 4 and c.vigproc_ms > 0 and c.peer_ms > 0 and np.isfinite(c.ratio)
        assert 0 <= c.fallbacks <= 2 and 0 <= c.off_centre <= 2
    assert r.peer_floor_ms >= 0
    # a frame with no vignetting and little structure is left alone
    assert r.cases[CASES.index("none")].fallbacks == 2


def test_api_speed_without_a_peer_states_no_ratio():
    rng = np.random.default_rng(1)
    r = api_speed([0.3 + 0.4 * rng.random((320, 480, 3))], None, rounds=1, cases=("none",))
    assert len(r.cases) == 1 and r.cases[0].vigproc_ms > 0
    assert np.isnan(r.cases[0].peer_ms) and np.isnan(r.cases[0].ratio) and np.isnan(r.peer_floor_ms)


def test_the_command_runs_without_a_peer(tmp_path, monkeypatch, capsys):
    """``vigproc bench speed --api`` with no peer given or in the environment: the
    vigproc column alone, exit 0 (it once failed looking the environment up)."""
    from benchmarks.peers import PEER_ENV
    from vigproc.frontends.cli import main
    from vigproc.io.images import write_image

    monkeypatch.delenv(PEER_ENV, raising=False)
    rng = np.random.default_rng(2)
    frame = (0.25 + 0.5 * rng.random((800, 1200, 3))).astype(np.float32)
    write_image(tmp_path / "frame.jpg", frame, bit_depth="uint8", transfer="srgb", quality=95)
    assert main(["bench", "speed", "--api", "--images", str(tmp_path), "--limit", "1", "--repeat", "1"]) == 0
    out = capsys.readouterr().out
    assert "no peer" in out and "none" in out
