"""A DICOM storage SCP in its own process (pynetdicom), standing in for a PACS or a dose registry.

    python tests/dicom_receiver.py AE_TITLE OUT_DIR [--hold N S] [--port P] [--tls CERT KEY]

Listens on 127.0.0.1 at port P (default: a free one) and prints "listening PORT". Only its own AE title is
accepted as the called AE. Each C-STORE is written to OUT_DIR/<SOP Instance UID>.dcm and its
UID appended to OUT_DIR/received.txt (flushed and fsynced) as soon as it arrives; the answer
to the N-th object received is held back S seconds (--hold), so a test can kill the sender
while it waits for it. With
--tls it speaks DICOM over TLS with that certificate and key (PEM).
"""

import argparse
import logging
import os
import ssl
import sys
import time

from pynetdicom import AE, AllStoragePresentationContexts, evt
from pynetdicom.sop_class import Verification  # type: ignore[attr-defined]


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("ae_title")
    parser.add_argument("out_dir")
    parser.add_argument("--hold", nargs=2, type=float, default=(0, 0), metavar=("N", "S"))
    parser.add_argument("--port", type=int, default=0)
    parser.add_argument("--tls", nargs=2, metavar=("CERT", "KEY"))
    args = parser.parse_args()
    logging.getLogger("pynetdicom").setLevel(logging.CRITICAL)
    os.makedirs(args.out_dir, exist_ok=True)
    log = open(os.path.join(args.out_dir, "received.txt"), "a", encoding="ascii")

    count = [0]

    def on_store(event):
        ds = event.dataset
        ds.file_meta = event.file_meta
        uid = str(ds.SOPInstanceUID)
        ds.save_as(os.path.join(args.out_dir, f"{uid}.dcm"), enforce_file_format=True)
        log.write(uid + "\n")
        log.flush()
        os.fsync(log.fileno())
        count[0] += 1
        if count[0] == int(args.hold[0]):
            time.sleep(args.hold[1])
        return 0x0000

    ae = AE(ae_title=args.ae_title)
    ae.require_called_aet = True
    ae.supported_contexts = AllStoragePresentationContexts
    ae.add_supported_context(Verification)
    context = None
    if args.tls:
        context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
        context.load_cert_chain(*args.tls)
    server = ae.start_server(("127.0.0.1", args.port), block=False, evt_handlers=[(evt.EVT_C_STORE, on_store)],
                             ssl_context=context)
    print(f"listening {server.server_address[1]}", flush=True)
    try:
        sys.stdin.read()      # until the test closes our stdin (or kills us)
    finally:
        server.shutdown()


if __name__ == "__main__":
    main()
