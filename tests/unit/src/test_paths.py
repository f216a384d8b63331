"""src.utils.paths.without_folder: a committed record names no path of this machine."""

from src.utils.paths import without_folder


def test_a_folder_is_written_as_its_placeholder_in_both_spellings_and_only_as_a_whole_name(tmp_path):
    run = tmp_path / "pointnetlk"
    (tmp_path / "link").symlink_to(tmp_path)
    text = f"dir={run} ckpt={run}/best.ckpt linked={tmp_path / 'link' / 'pointnetlk'} \"{run}\" other={run}_revisited/x"
    linked = tmp_path / "link" / "pointnetlk"
    assert without_folder(without_folder(text, run, "RUN"), linked, "RUN") == (
        f"dir=RUN ckpt=RUN/best.ckpt linked=RUN \"RUN\" other={run}_revisited/x")
