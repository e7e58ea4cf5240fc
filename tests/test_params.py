"""MergeParams: groups by stage, every field also set and read by its own name."""

import dataclasses

import pytest

from pgvd.params import DecisionParams, MergeParams, OffParams, SearchParams


def test_a_field_named_alone_goes_to_its_group():
    p = MergeParams(diagnostics=False, min_margin=0.6, rho=0.8, probabilistic=False)
    assert p.decision.min_margin == 0.6 and p.search.rho == 0.8
    assert p.off.probabilistic is False and p.diagnostics is False
    # the rest of each group keeps its defaults
    assert p.decision.margin_noise == DecisionParams().margin_noise
    assert p.search.max_edges == SearchParams().max_edges


def test_replace_takes_field_names_and_keeps_the_others():
    base = MergeParams(diagnostics=False, heading_span=6.0)
    p = dataclasses.replace(base, min_agreement=0.9)
    assert p.decision.min_agreement == 0.9
    assert p.off.heading_span == 6.0 and p.diagnostics is False
    assert p == MergeParams(diagnostics=False, heading_span=6.0, min_agreement=0.9)


def test_a_group_and_a_field_of_it_combine():
    p = MergeParams(off=OffParams(heading_span=6.0), heading_step=2.0)
    assert (p.off.heading_span, p.off.heading_step) == (6.0, 2.0)


def test_a_field_reads_by_its_own_name():
    p = MergeParams(drift_shift=0.5)
    assert p.drift_shift == p.decision.drift_shift == 0.5
    assert p.search_weights == p.off.search_weights


def test_unknown_names_are_refused_with_the_name():
    with pytest.raises(TypeError, match="no_such_field"):
        MergeParams(no_such_field=1)
    # a property of a group is read by name but is no field to set
    with pytest.raises(TypeError, match="search_weights"):
        MergeParams(search_weights=None)
    with pytest.raises(AttributeError, match="no_such_field"):
        MergeParams().no_such_field  # noqa: B018


def test_field_names_are_every_field_of_every_group_once():
    names = MergeParams.field_names()
    params = MergeParams()
    groups = [getattr(params, f.name) for f in dataclasses.fields(params)]
    groups = [g for g in groups if dataclasses.is_dataclass(g)]
    expected = {f.name for g in groups for f in dataclasses.fields(g)}
    assert len(names) == len(set(names))
    assert set(names) == expected | {"diagnostics"}
