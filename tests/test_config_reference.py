"""docs/configuration.md is generated from the schema (splat_slam_ros/config_reference.py):
up to date, complete (every key with its default and a description), and the comment
association it relies on works on made-up sources."""
import dataclasses
import textwrap

import yaml

from splat_slam_ros import config_reference as ref
from splat_slam_ros.config import SlamConfig

DOC = ref.DEFAULT_OUT


def table_rows(text):
    """{key: (type, default, description)} of the key tables in the Markdown text."""
    out = {}
    for line in text.splitlines():
        if line.startswith("| `") and line.count(" | ") >= 3:
            key, typ, default, desc = [c.strip() for c in
                                       line.strip("| ").replace("\\|", "\0").split(" | ")][:4]
            out[key.strip("`")] = (typ, default.strip("`"), desc.replace("\0", "|"))
    return out


def test_reference_is_up_to_date(capsys):
    assert DOC.is_file(), f"{DOC} missing: run python -m splat_slam_ros.config_reference"
    assert DOC.read_text() == ref.render(), (
        "docs/configuration.md is stale: run python -m splat_slam_ros.config_reference")
    assert ref.main(["--check"]) == 0


def test_check_flags_a_stale_file(tmp_path, capsys):
    out = tmp_path / "configuration.md"
    assert ref.main(["--check", "--out", str(out)]) == 1          # missing
    assert ref.main(["--out", str(out)]) == 0 and out.read_text() == ref.render()
    assert ref.main(["--check", "--out", str(out)]) == 0
    out.write_text(out.read_text().replace("tracking.keyframe_thresh", "tracking.kf_thresh"))
    assert ref.main(["--check", "--out", str(out)]) == 1
    assert "stale" in capsys.readouterr().err


def test_every_key_is_listed_with_its_default():
    listed = table_rows(DOC.read_text())
    flat = SlamConfig().flat()
    assert set(listed) == set(flat), (
        f"missing: {sorted(set(flat) - set(listed))}, extra: {sorted(set(listed) - set(flat))}")
    for key, value in flat.items():
        shown = yaml.safe_load(listed[key][1])     # the default as a user would type it
        assert shown == value and type(shown) is type(value), (key, listed[key][1], value)
    assert listed["mapping.raster_backend"][2].endswith(
        "Choices: `auto`, `cpp`, `torch`, `gsplat`")


def test_every_key_has_a_description():
    missing = [r["key"] for _, _, items in ref.rows() for r in items if not r["description"]]
    assert not missing, f"add a comment beside these fields in config.py: {missing}"
    sections = [name for name, text, _ in ref.rows() if name and not text]
    assert not sections, f"add a docstring to these config sections: {sections}"


def test_presets_table_lists_the_changed_keys():
    text = DOC.read_text()
    paper = next(ln for ln in text.splitlines() if ln.startswith("| `paper` |"))
    assert "`mapping.iters_per_keyframe: 60`" in paper and "`mapping.iters_first: 1050`" in paper
    assert "mapping.window_size" not in paper                # unchanged keys are not listed
    tum = dict((p, (first, ch)) for p, first, ch in ref.presets())["tum.yaml"]
    assert tum[0].startswith("TUM RGB-D") and "camera.crop: 8" in tum[1]


SOURCE = textwrap.dedent('''
    @dataclass
    class Made:
        """A made-up section."""

        # a group comment, apart from the next field

        # above a, first line
        # above a, second line
        a: int = 1              # beside a
        b: float = 2.0          # beside b, its
                                # continuation
        # above c
        c: str = "x"
        d: bool = True
        e: tuple = field(default=(1, 2),
                         metadata={})   # beside the last line of e
                                        # and e's continuation
                                # not aligned: nobody's
        f: int = 0              # a hyphen-
                                # ated word

    class Bare:
        # a leading block comment

        g: int = 0
        # note on h
        h: int = 0
''')


def test_comment_association():
    docs = ref.field_docs(SOURCE)
    text, made = docs["Made"]
    assert text == "A made-up section."
    assert made == {
        "a": "above a, first line above a, second line; beside a",
        "b": "beside b, its continuation",
        "c": "above c",
        "d": "",
        "e": "beside the last line of e and e's continuation",
        "f": "a hyphen-ated word",
    }
    text, bare = docs["Bare"]
    assert text == "a leading block comment"
    assert bare == {"g": "", "h": "note on h"}


def test_sentence_joining_and_values():
    assert ref._sentences("group note. More.", "beside") == "group note. More. Beside"
    assert ref._sentences("group (x)", "beside") == "group (x); beside"
    assert ref._sentences("", "time_budget: y") == "time_budget: y"
    assert ref._sentences("a.", "time_budget: y") == "a. time_budget: y"
    for v in (True, 0, -1, 1e-5, 0.0002, 3.0, "", "auto", (7, 12)):
        back = yaml.safe_load(ref.format_value(v))
        assert back == (list(v) if isinstance(v, tuple) else v), v
    assert ref.first_sentence("# One (a.b; c). Two.\n# three\nkey: 1\n# later") == "One (a.b; c)."


def test_schema_fields_are_the_documented_ones():
    """rows() walks the dataclasses themselves: a field added to a section shows up."""
    for name, _, items in ref.rows():
        if name:
            cls = type(getattr(SlamConfig(), name))
            assert [r["key"] for r in items] == [f"{name}.{f.name}"
                                                 for f in dataclasses.fields(cls)]
