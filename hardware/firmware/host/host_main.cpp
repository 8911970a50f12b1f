// main() of the host build: setup() once, then loop() until stdin closes.
#include <poll.h>
#include <time.h>
#include <unistd.h>

#include "Arduino.h"

HostSerial Serial;
static int pending = -1;  // one byte of look-ahead for available()/read()
static bool eof = false;

static unsigned long long nowUs() {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (unsigned long long)ts.tv_sec * 1000000ULL + ts.tv_nsec / 1000;
}
static const unsigned long long startUs = nowUs();
unsigned long micros() { return (unsigned long)(nowUs() - startUs); }
unsigned long millis() { return (unsigned long)((nowUs() - startUs) / 1000); }

int HostSerial::available() {
  if (pending >= 0) return 1;
  struct pollfd p = {0, POLLIN, 0};
  if (poll(&p, 1, 1) > 0) {  // 1 ms: keeps the loop from spinning a core
    unsigned char c;
    ssize_t n = ::read(0, &c, 1);
    if (n == 1) { pending = c; return 1; }
    eof = true;
  }
  return 0;
}
int HostSerial::read() {
  if (!available()) return -1;
  int c = pending;
  pending = -1;
  return c;
}

void pinMode(uint8_t, uint8_t) {}
void digitalWrite(uint8_t, uint8_t) {}
void analogWrite(uint8_t, int) {}
void attachInterrupt(int, void (*)(), int) {}
int digitalRead(uint8_t pin) {
  const char *flag = getenv("FIRMWARE_INTERLOCK_FILE");
  if (pin == 3 && flag && access(flag, F_OK) == 0) return HIGH;  // interlock open
  return LOW;
}

void setup();
void loop();

int main() {
  setup();
  while (!eof) loop();
  return 0;
}
