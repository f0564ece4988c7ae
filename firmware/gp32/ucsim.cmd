# shc08 start-up commands for the LSU firmware (lsu gp32 firmware run)
# the GP32's RAM is 0x40-0x23f and the stack grows down from 0x23f: below 0x40 it would overwrite the I/O registers
sp_limit=0x40
