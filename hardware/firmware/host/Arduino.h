// Host (Linux) build of the controller firmware: just enough of the Arduino API to run
// fringescope_controller.ino as a process whose stdin/stdout is the serial line.
// Used by the tests to drive the REAL firmware source with the Python driver over a pty.
// Inputs: the interlock reads "open" while the file named by $FIRMWARE_INTERLOCK_FILE exists.
#pragma once
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define HIGH 1
#define LOW 0
#define INPUT 0
#define OUTPUT 1
#define INPUT_PULLUP 2
#define RISING 3
#define F(s) (reinterpret_cast<const __FlashStringHelper *>(s))
#define digitalPinToInterrupt(p) ((p) == 2 ? 0 : (p) == 3 ? 1 : -1)

class __FlashStringHelper;

class HostSerial {
 public:
  void begin(unsigned long) {}
  int available();
  int read();
  void print(const char *s) { fputs(s, stdout); flush(); }
  void print(const __FlashStringHelper *s) { print(reinterpret_cast<const char *>(s)); }
  void print(char c) { fputc(c, stdout); flush(); }
  void print(int v) { printf("%d", v); flush(); }
  void print(unsigned int v) { printf("%u", v); flush(); }
  void print(long v) { printf("%ld", v); flush(); }
  void print(unsigned long v) { printf("%lu", v); flush(); }
  template <typename T> void println(T v) { print(v); print('\n'); }
  void println() { print('\n'); }
 private:
  void flush() { fflush(stdout); }
};
extern HostSerial Serial;

unsigned long millis();
unsigned long micros();
void pinMode(uint8_t, uint8_t);
void digitalWrite(uint8_t, uint8_t);
int digitalRead(uint8_t pin);
void analogWrite(uint8_t pin, int value);
void attachInterrupt(int, void (*)(), int);
inline void noInterrupts() {}
inline void interrupts() {}
