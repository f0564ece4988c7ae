"""GP32 serial protocol codec, pyserial client, GP32 emulator (pty) and the gp32_driver node."""
