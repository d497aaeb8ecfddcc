"""The appliance profile's dicom: section: broken ones are refused with file, line and field."""

import re

import pytest
from test_profiles_broken import APPLIANCE, Broken, make_broken, replace

from appliance.cli import main

DESTINATIONS = "  destinations: []            # e.g."
PACS = "  destinations:\n    - {name: pacs, ae_title: PACS, host: 127.0.0.1, port: 4242}\n    #"

CASES = [
    Broken("ae-title-too-long", APPLIANCE, replace("  ae_title: FLUOROSIM\n", "  ae_title: FLUOROSIM-APPLIANCE-3\n"),
           "FLUOROSIM-APPLIANCE-3", "dicom.ae_title"),
    Broken("ae-title-with-backslash", APPLIANCE, replace("  ae_title: FLUOROSIM\n", "  ae_title: 'FLUORO\\SIM'\n"),
           "FLUORO", "dicom.ae_title"),
    Broken("station-name-too-long", APPLIANCE, replace("  station_name: FLUOROSIM\n", "  station_name: FLUOROSIM-TRAINING-ROOM-2\n"),
           "FLUOROSIM-TRAINING-ROOM-2", "dicom.station_name"),
    Broken("port-zero", APPLIANCE, replace(DESTINATIONS, PACS.replace("port: 4242", "port: 0")), "port: 0",
           "dicom.destinations[0].port"),
    Broken("unknown-objects", APPLIANCE, replace(DESTINATIONS, PACS.replace("port: 4242}", "port: 4242, objects: xrays}")),
           "objects: xrays", "dicom.destinations[0].objects"),
    Broken("destination-typo", APPLIANCE, replace(DESTINATIONS, PACS.replace("host:", "hots:")), "hots:",
           "dicom.destinations[0].hots"),
    Broken("same-name-twice", APPLIANCE, replace(DESTINATIONS, PACS + "\n    - {name: pacs, ae_title: REG, host: b, port: 104}\n    #"),
           "  destinations:", "destination name 'pacs' is used twice"),
    Broken("tls-cert-without-key", APPLIANCE,
           replace(DESTINATIONS, PACS.replace("port: 4242}", "port: 4242, tls: {ca_file: ca.pem, cert_file: me.pem}}")),
           "tls:", "dicom.destinations[0].tls"),
    Broken("retry-zero", APPLIANCE, replace("    first_delay_s: 10 ", "    first_delay_s: 0 "), "first_delay_s: 0",
           "dicom.retry.first_delay_s"),
]


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.name)
def test_broken_dicom_section_is_refused_with_file_line_and_field(case: Broken, tmp_path, capsys):
    target, validated, content = make_broken(case, tmp_path)
    assert main(["validate", str(validated)]) == 2
    _, err = capsys.readouterr()
    mine = [line for line in err.splitlines() if line.startswith(f"{target}:")]
    assert mine and "Traceback" not in err, err
    assert any(case.field in line for line in mine), f"expected {case.field!r} in {mine}"
    expected = case.line(content if isinstance(content, str) else content.decode())
    assert any(re.match(rf"{re.escape(str(target))}:{expected}: ", line) for line in mine), (expected, mine)


def test_the_shipped_section_validates_and_a_destination_can_be_added(tmp_path, capsys):
    case = Broken("fine", APPLIANCE, replace(DESTINATIONS, PACS), None, "")
    _, validated, _ = make_broken(case, tmp_path)
    assert main(["validate", str(validated)]) == 0, capsys.readouterr().err
