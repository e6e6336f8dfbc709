"""What an extension costs, counted by adding a throwaway one.

Each section adds one kind of extension the way docs/design.md says to, inside a test, and checks that it
works end to end. The sections are self-contained (their imports inside the tests).
"""

from __future__ import annotations

# ---------------------------------------------------------------------------------------------------------
# A [[serve]] key: one field of the serving options (plus its row in docs/case-toml.md's table).
# ---------------------------------------------------------------------------------------------------------


def test_a_serve_key_is_one_field_of_the_serving_options(tmp_path, monkeypatch):
    from dataclasses import dataclass

    import pytest

    import latticedft._serve
    from latticedft import ConfigError
    from latticedft._case import _schema, load_case
    from latticedft._pipeline import check_case, serve_task, train_model
    from latticedft._serve._options import ServeOptions, choice, option

    from case_helpers import tiny_wave

    @dataclass(frozen=True)
    class FlavouredOptions(ServeOptions):
        """The serving options with one more ``[[serve]]`` key: all that a new key needs in the code."""

        flavour: str = option("plain", choice("plain", "spicy"))

    case = tiny_wave(tmp_path)
    with pytest.raises(ConfigError, match=r"serve\[0\]\.flavour: unknown key"):
        load_case(case, ["serve.test.flavour=spicy"])  # not a key before it is a field

    monkeypatch.setattr(_schema, "SERVE_OPTIONS", FlavouredOptions)
    assert load_case(case).serve[0].options.flavour == "plain"  # the field's default
    c = load_case(case, ["serve.test.flavour=spicy"])
    assert c.serve[0].options.flavour == "spicy" and c.serve[0].options.rtol == 1e-10
    with pytest.raises(ConfigError) as bad:
        load_case(case, ["serve.test.flavour=mild"])
    assert str(bad.value) == "--set: serve[0].flavour: expected 'plain' or 'spicy', got 'mild'"
    with pytest.raises(ConfigError, match=r"serve\[0\]\.flavor: unknown key; did you mean 'flavour'\?"):
        load_case(case, ["serve.test.flavor=spicy"])

    seen: list[ServeOptions] = []
    real = latticedft._serve.serve

    def spy(*args, **kwargs):
        seen.append(kwargs["options"])
        return real(*args, **kwargs)

    monkeypatch.setattr(latticedft._serve, "serve", spy)  # the pipeline's serving call
    data = check_case(c)
    model, _ = train_model(c, data)
    out = serve_task(model, data.tasks[0])
    assert out.complete and [type(o) for o in seen] == [FlavouredOptions] and seen[0].flavour == "spicy"
