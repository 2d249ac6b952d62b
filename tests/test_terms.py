"""The term interface: the registry matches the configuration's vocabulary, and every sampled
image keeps the random-number stream it has always had."""
from dataclasses import fields

from psdr_cli.config.estimator_section import EstimatorConfig
from psdr_cli.config.vocabularies import TERMS
from psdr_cli.estimators import registry
from psdr_cli.guiding.auto import GUIDED_TERMS
from psdr_cli.guiding.targets import Guides


def test_registry_lists_the_configured_terms_in_order():
    assert tuple(t.name for t in registry.TERMS) == TERMS
    keys = {f.name for f in fields(EstimatorConfig)}
    assert all(t.samples_key in keys for t in registry.TERMS)
    assert GUIDED_TERMS == registry.GUIDED == ("direct", "indirect")


def test_streams_are_unchanged():
    """Seeds are hashes of the stream: changing a number changes every estimate."""
    assert {t.name: t.stream for t in registry.TERMS} == {"interior": 1, "primary": 2, "direct": 3, "indirect": 4}
    assert (registry.RENDER_STREAM, registry.MITSUBA_STREAM, registry.ADJOINT_STREAM) == (0, 9, 10)
    assert {t.name: t.samples_key for t in registry.TERMS} == {
        "interior": "spp", "primary": "primary_spp", "direct": "boundary_spp", "indirect": "boundary_spp"}


def test_guides_are_keyed_by_term():
    guides = Guides(direct={"light": "g1"}, indirect="g2")
    assert guides["direct"] == {"light": "g1"} and guides["indirect"] == "g2" and guides.get("primary") is None
    assert guides.all() == [("direct/light", "g1"), ("indirect/dir", "g2")]
    assert Guides().get("direct") is None and Guides().all() == []
