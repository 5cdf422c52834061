"""Atomic writes: complete or absent, never over an input when asked not to."""

from __future__ import annotations

import os
import stat

import pytest

from deltar.io.atomic import atomic_path, write_text_atomic


def test_written_file_has_normal_permissions_and_no_temporary_left(tmp_path):
    target = write_text_atomic(tmp_path / "a" / "out.json", "{}")
    assert target.read_text() == "{}"
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(target.stat().st_mode) == 0o666 & ~umask
    assert [p.name for p in target.parent.iterdir()] == ["out.json"]


def test_failure_leaves_the_previous_file_untouched(tmp_path):
    target = write_text_atomic(tmp_path / "out.txt", "old")
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("writer crashed")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]


def test_refuses_to_overwrite_when_asked(tmp_path):
    target = write_text_atomic(tmp_path / "input.txt", "keep")
    with pytest.raises(FileExistsError, match=r"input\.txt"):
        write_text_atomic(target, "new", overwrite=False)
    assert target.read_text() == "keep"


@pytest.mark.parametrize("hard_links", [True, False])
def test_a_file_made_by_another_process_while_writing_is_never_replaced(tmp_path, monkeypatch,
                                                                         hard_links):
    import errno

    import deltar.io.atomic as atomic

    target = tmp_path / "out.txt"
    # The other writer finishes in the last moment: after this write checked, before it
    # moves its file into place (with hard links the move itself refuses).
    link = os.link

    def other_writer_first(source, destination):
        target.write_text("theirs")
        if not hard_links:
            raise OSError(errno.EPERM, "hard links not supported")
        return link(source, destination)

    monkeypatch.setattr(atomic.os, "link", other_writer_first)
    with pytest.raises(FileExistsError, match=r"out\.txt"):
        write_text_atomic(target, "mine", overwrite=False)
    assert target.read_text() == "theirs"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]
    # Without the refusal asked for, the file is replaced as before.
    write_text_atomic(target, "mine")
    assert target.read_text() == "mine"


def test_a_full_disk_is_reported_naming_the_output_and_leaves_nothing(tmp_path):
    import errno

    import pytest

    from deltar.io.atomic import atomic_path

    target = tmp_path / "out.bin"
    with pytest.raises(OSError) as caught, atomic_path(target):
        raise OSError(errno.ENOSPC, "No space left on device")
    assert (caught.value.errno, caught.value.filename) == (errno.ENOSPC, str(target))
    assert list(tmp_path.iterdir()) == []


def test_a_write_whose_clean_up_was_skipped_leaves_no_temporary_at_exit(tmp_path):
    """A stop can land inside the clean-up itself; the exit hook removes what it left."""
    from deltar.io.atomic import leftover_temporaries, remove_unfinished_temporaries

    unfinished = atomic_path(tmp_path / "out.png")
    tmp = unfinished.__enter__()  # never exited: as if a stop skipped the clean-up
    tmp.write_bytes(b"half")
    assert leftover_temporaries(tmp_path, ".png") == [tmp]
    remove_unfinished_temporaries()
    assert list(tmp_path.iterdir()) == []
    finished = write_text_atomic(tmp_path / "kept.txt", "whole")
    remove_unfinished_temporaries()  # finished outputs are not its business
    assert [p.name for p in tmp_path.iterdir()] == [finished.name]


def test_a_staging_folder_is_removed_whatever_ends_it(tmp_path):
    """Left by success, by an exception, or (its clean-up skipped) at exit."""
    from deltar.io.atomic import remove_unfinished_temporaries, staging_folder

    with staging_folder(tmp_path / "out_bag") as staging:
        (staging / "out_bag").mkdir()
        (staging / "out_bag" / "data.db3").write_bytes(b"rows")
        (staging / "out_bag").rename(tmp_path / "out_bag")
    with pytest.raises(KeyboardInterrupt), staging_folder(tmp_path / "other") as staging:
        (staging / "half.db3").write_bytes(b"half")
        raise KeyboardInterrupt
    unfinished = staging_folder(tmp_path / "third")
    (unfinished.__enter__() / "half.db3").write_bytes(b"half")  # never exited
    remove_unfinished_temporaries()
    assert [p.name for p in tmp_path.iterdir()] == ["out_bag"]


def test_prove_writable_leaves_nothing_and_says_why_it_cannot(tmp_path):
    from deltar.io import atomic

    atomic.prove_writable(tmp_path)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(OSError) as caught:
        atomic.prove_writable(tmp_path / "missing")
    assert caught.value.strerror  # the system's reason, for the message
    assert not atomic._UNFINISHED  # nothing left registered either way
