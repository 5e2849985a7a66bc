"""The tooling's ``semcal`` sub-commands; ``semcal_ros.cli`` discovers them beside its own."""
