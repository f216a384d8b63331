"""src.utils.paths.without_folder: a committed record names no path of this machine; with_folder writes it back."""

from src.utils.paths import with_folder, without_folder


def test_a_folder_is_written_as_its_placeholder_in_both_spellings_and_only_as_a_whole_name(tmp_path):
    run = tmp_path / "pointnetlk"
    (tmp_path / "link").symlink_to(tmp_path)
    text = f"dir={run} ckpt={run}/best.ckpt linked={tmp_path / 'link' / 'pointnetlk'} \"{run}\" other={run}_revisited/x"
    linked = tmp_path / "link" / "pointnetlk"
    assert without_folder(without_folder(text, run, "RUN"), linked, "RUN") == (
        f"dir=RUN ckpt=RUN/best.ckpt linked=RUN \"RUN\" other={run}_revisited/x")


def test_a_placeholder_is_written_back_as_the_folder_only_where_it_starts_a_path(tmp_path):
    text = "dir=RUNS ckpt=RUNS/a/best.ckpt \"RUNS\" RUNS_OLD/x /srv/RUNS/x MYRUNS"
    assert with_folder(text, tmp_path, "RUNS") == (
        f"dir={tmp_path} ckpt={tmp_path}/a/best.ckpt \"{tmp_path}\" RUNS_OLD/x /srv/RUNS/x MYRUNS")
    assert without_folder(with_folder(text, tmp_path, "RUNS"), tmp_path, "RUNS") == text
