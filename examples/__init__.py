"""Tasks of a user's own, written from docs/offload.md alone: installed as dynqos.examples so that the
shipped scenarios can fly them (dynqos demo --scenario offload-example)."""
