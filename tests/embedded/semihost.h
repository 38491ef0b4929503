/* Output and exit of the harness: ARM semihosting on bare metal, stdio on Linux. */
#ifndef SEMIHOST_H
#define SEMIHOST_H

/* Write a NUL-terminated string to the host's standard output. */
void semihost_write0(const char *text);
/* End the program: status 0 is success, anything else a failure. */
void semihost_exit(int status) __attribute__((noreturn));

#endif
