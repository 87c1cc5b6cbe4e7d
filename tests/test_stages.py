"""The per-scene stage cache with two writers of the same stage (two runs sharing a cache)."""
from selfseg.stages import StageCache

KEY = {"stage": "recon", "config": 1}


def test_first_writer_wins_and_stagings_do_not_clobber(tmp_path):
    cache = StageCache(tmp_path)
    with cache.write("recon", "000000", KEY) as late:  # started first, finishes last
        (late / "cloud.txt").write_text("late")
        # a second writer (another process in real use; here nested) completes meanwhile
        with cache.write("recon", "000000", KEY) as early:
            assert early != late  # each writer stages in its own folder
            (early / "cloud.txt").write_text("early")
        assert (late / "cloud.txt").read_text() == "late"  # the other writer did not remove our files
    final = cache.path("recon", "000000")
    assert cache.is_valid("recon", "000000", KEY)
    assert (final / "cloud.txt").read_text() == "early"  # a valid stage never changes under a reader
    assert sorted(p.name for p in final.parent.iterdir()) == ["000000"]  # no staging folder left


def test_stale_output_is_replaced(tmp_path):
    cache = StageCache(tmp_path)
    with cache.write("recon", "000000", {"config": 0}) as tmp:
        (tmp / "cloud.txt").write_text("old")
    with cache.write("recon", "000000", KEY) as tmp:
        (tmp / "cloud.txt").write_text("new")
    assert (cache.path("recon", "000000") / "cloud.txt").read_text() == "new"
    assert cache.is_valid("recon", "000000", KEY) and not cache.is_valid("recon", "000000", {"config": 0})
