"""``python -m shared.messages.wiredoc`` (``make wire-docs``): write or ``--check`` the wire docs."""

from shared.messages.wiredoc import main

raise SystemExit(main())
