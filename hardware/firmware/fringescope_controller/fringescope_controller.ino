// Fringescope LED/trigger controller firmware — protocol 1.0 (hardware/PROTOCOL.md).
//
// Board: Arduino Uno / Nano (ATmega328P, 16 MHz); pins in hardware/WIRING.md.
// - R/G/B LED driver channels: one lit at a time, current as PWM duty (0-1000 per-mille).
// - Camera trigger out: INT mode times TCNT pulses every TPER us; PASS mode relays each
//   projector trigger edge after TDLY us. Pulse width TWID us.
// - Interlock in (closed = pulled to GND = safe): open forces LEDs off and disarms.
// - Watchdog: LEDs off + disarm when no accepted command for WDT ms while active.
// The Python emulator app/devices/controller_emulator.py implements the same behaviour.

#include <Arduino.h>
#include <avr/wdt.h>

static const char PROTOCOL_VERSION[] = "1.0";
static const char FIRMWARE_VERSION[] = "1.0.0";
static const char SERIAL_NUMBER[] = "FS0001";  // set per unit before flashing

static const uint8_t PIN_LED[3] = {9, 10, 11};   // R, G, B PWM -> LED driver DIM inputs
static const uint8_t PIN_CAM_TRIGGER = 7;        // camera trigger out (active high)
static const uint8_t PIN_PROJ_TRIGGER = 2;       // projector trigger in (INT0, rising edge)
static const uint8_t PIN_INTERLOCK = 3;          // interlock loop to GND, INPUT_PULLUP
static const uint8_t PIN_STATUS = 13;            // on while armed
static const uint8_t MAX_LINE = 63;
static const char CHANNELS[3] = {'R', 'G', 'B'};

// --- state (defaults as in PROTOCOL.md) -------------------------------------------
static int8_t ledOn = -1;              // -1 = all off, else 0..2
static uint16_t currentPermille[3] = {0, 0, 0};
static bool armed = false;
static bool passMode = false;
static uint32_t periodUs = 20000, delayUs = 0, widthUs = 100;
static uint16_t pulseCount = 16;
static uint32_t wdtMs = 2000;
static bool tripped = false;
static bool interlockOpen = false;
static uint32_t lastOkMs = 0;
static uint32_t pulsesDone = 0;

// trigger scheduling (micros() based; jitter ~4-8 us from loop latency)
static uint32_t nextStartUs = 0;       // INT: start of the next period
static bool pulsePending = false;      // a pulse is scheduled at pulseAtUs
static uint32_t pulseAtUs = 0;
static bool pulseHigh = false;
static uint32_t pulseEndUs = 0;
static volatile bool projEdge = false;
static volatile uint32_t projEdgeUs = 0;

static char line[MAX_LINE + 1];
static uint8_t lineLen = 0;
static bool lineOverflow = false;

static void applyLeds() {
  for (uint8_t c = 0; c < 3; c++) {
    uint16_t duty = (ledOn == (int8_t)c && !interlockOpen) ? (uint32_t)currentPermille[c] * 255 / 1000 : 0;
    analogWrite(PIN_LED[c], duty);
  }
}

static void disarm() {
  armed = false;
  pulsePending = false;
  pulseHigh = false;
  digitalWrite(PIN_CAM_TRIGGER, LOW);
  digitalWrite(PIN_STATUS, LOW);
}

static void resetDefaults() {
  ledOn = -1;
  for (uint8_t c = 0; c < 3; c++) currentPermille[c] = 0;
  disarm();
  passMode = false;
  periodUs = 20000; delayUs = 0; widthUs = 100; pulseCount = 16; wdtMs = 2000;
  tripped = false;
  pulsesDone = 0;
  applyLeds();
}

static void onProjectorEdge() {
  projEdgeUs = micros();
  projEdge = true;
}

// --- replies -------------------------------------------------------------------------
static void ok() { Serial.println(F("OK")); }
static void err(uint8_t code, const __FlashStringHelper *msg) {
  Serial.print(F("ERR ")); Serial.print(code); Serial.print(' '); Serial.println(msg);
}

// Parse a decimal unsigned integer within [lo, hi]; false on junk or out of range.
static bool parseRange(const char *s, uint32_t lo, uint32_t hi, uint32_t *out) {
  if (!s || !*s) return false;
  uint32_t v = 0;
  for (const char *p = s; *p; p++) {
    if (*p < '0' || *p > '9') return false;
    v = v * 10 + (uint32_t)(*p - '0');
    if (v > 100000000UL) return false;
  }
  if (v < lo || v > hi) return false;
  *out = v;
  return true;
}

static int8_t parseChannel(const char *s) {
  if (!s || s[1] != '\0') return -1;
  for (uint8_t c = 0; c < 3; c++) if (s[0] == CHANNELS[c]) return c;
  return -1;
}

// Execute one command; returns true if it was accepted (OK), which feeds the watchdog.
static bool execute(char *text) {
  char *argv[4];
  uint8_t argc = 0;
  for (char *tok = strtok(text, " "); tok && argc < 4; tok = strtok(NULL, " ")) argv[argc++] = tok;
  if (argc == 0) { err(1, F("empty line")); return false; }
  const char *cmd = argv[0];
  uint8_t nargs = argc - 1;
  uint32_t v;
#define NARGS(n) if (nargs != (n)) { err(2, F("wrong argument count")); return false; }

  if (!strcmp(cmd, "*IDN?")) {
    NARGS(0);
    Serial.print(F("OK FRINGESCOPE,LEDCTRL,")); Serial.print(SERIAL_NUMBER);
    Serial.print(','); Serial.println(FIRMWARE_VERSION);
    return true;
  }
  if (!strcmp(cmd, "VER?")) { NARGS(0); Serial.print(F("OK ")); Serial.println(PROTOCOL_VERSION); return true; }
  if (!strcmp(cmd, "*RST")) { NARGS(0); resetDefaults(); ok(); return true; }
  if (!strcmp(cmd, "HB")) { NARGS(0); ok(); return true; }
  if (!strcmp(cmd, "LED")) {
    NARGS(1);
    if (!strcmp(argv[1], "OFF")) { ledOn = -1; applyLeds(); ok(); return true; }
    int8_t c = parseChannel(argv[1]);
    if (c < 0) { err(3, F("channel must be R, G or B")); return false; }
    if (interlockOpen) { err(4, F("interlock open")); return false; }
    ledOn = c; tripped = false; applyLeds(); ok(); return true;
  }
  if (!strcmp(cmd, "LED?")) {
    NARGS(0);
    Serial.print(F("OK "));
    if (ledOn < 0) Serial.println(F("OFF")); else Serial.println(CHANNELS[ledOn]);
    return true;
  }
  if (!strcmp(cmd, "CUR")) {
    NARGS(2);
    int8_t c = parseChannel(argv[1]);
    if (c < 0 || !parseRange(argv[2], 0, 1000, &v)) { err(3, F("CUR R|G|B 0-1000")); return false; }
    currentPermille[c] = (uint16_t)v; applyLeds(); ok(); return true;
  }
  if (!strcmp(cmd, "CUR?")) {
    NARGS(1);
    int8_t c = parseChannel(argv[1]);
    if (c < 0) { err(3, F("channel must be R, G or B")); return false; }
    Serial.print(F("OK ")); Serial.println(currentPermille[c]); return true;
  }
  bool timing = !strcmp(cmd, "TMODE") || !strcmp(cmd, "TPER") || !strcmp(cmd, "TDLY") ||
                !strcmp(cmd, "TWID") || !strcmp(cmd, "TCNT");
  if (timing) {
    NARGS(1);
    if (armed) { err(7, F("disarm first")); return false; }
    if (!strcmp(cmd, "TMODE")) {
      if (!strcmp(argv[1], "INT")) passMode = false;
      else if (!strcmp(argv[1], "PASS")) passMode = true;
      else { err(3, F("mode must be INT or PASS")); return false; }
    } else if (!strcmp(cmd, "TPER")) {
      if (!parseRange(argv[1], 1000, 1000000UL, &v)) { err(3, F("TPER 1000-1000000")); return false; }
      periodUs = v;
    } else if (!strcmp(cmd, "TDLY")) {
      if (!parseRange(argv[1], 0, 100000UL, &v)) { err(3, F("TDLY 0-100000")); return false; }
      delayUs = v;
    } else if (!strcmp(cmd, "TWID")) {
      if (!parseRange(argv[1], 10, 100000UL, &v)) { err(3, F("TWID 10-100000")); return false; }
      widthUs = v;
    } else {
      if (!parseRange(argv[1], 0, 65535, &v)) { err(3, F("TCNT 0-65535")); return false; }
      pulseCount = (uint16_t)v;
    }
    ok();
    return true;
  }
  if (!strcmp(cmd, "WDT")) {
    NARGS(1);
    if (!parseRange(argv[1], 100, 60000, &v)) { err(3, F("WDT 100-60000")); return false; }
    wdtMs = v; ok(); return true;
  }
  if (!strcmp(cmd, "WDT?")) { NARGS(0); Serial.print(F("OK ")); Serial.println(wdtMs); return true; }
  if (!strcmp(cmd, "ARM")) {
    NARGS(0);
    if (interlockOpen) { err(4, F("interlock open")); return false; }
    if (tripped) { err(5, F("watchdog tripped; send LED to re-enable")); return false; }
    armed = true; pulsesDone = 0; pulsePending = false; pulseHigh = false;
    nextStartUs = micros();
    noInterrupts(); projEdge = false; interrupts();
    digitalWrite(PIN_STATUS, HIGH);
    ok();
    return true;
  }
  if (!strcmp(cmd, "DISARM")) { NARGS(0); disarm(); ok(); return true; }
  if (!strcmp(cmd, "STAT?")) {
    NARGS(0);
    Serial.print(F("OK led="));
    if (ledOn < 0) Serial.print(F("OFF")); else Serial.print(CHANNELS[ledOn]);
    Serial.print(F(" cur=")); Serial.print(currentPermille[0]); Serial.print('/');
    Serial.print(currentPermille[1]); Serial.print('/'); Serial.print(currentPermille[2]);
    Serial.print(F(" armed=")); Serial.print(armed ? 1 : 0);
    Serial.print(F(" mode=")); Serial.print(passMode ? F("PASS") : F("INT"));
    Serial.print(F(" intlk=")); Serial.print(interlockOpen ? F("open") : F("closed"));
    Serial.print(F(" wdt=")); Serial.print(tripped ? F("tripped") : F("ok"));
    Serial.print(F(" pulses=")); Serial.println(pulsesDone);
    return true;
  }
  err(1, F("unknown command"));
  return false;
#undef NARGS
}

// --- trigger generation ---------------------------------------------------------------
static void serviceTrigger() {
  uint32_t now = micros();
  if (pulseHigh) {
    if ((int32_t)(now - pulseEndUs) >= 0) { digitalWrite(PIN_CAM_TRIGGER, LOW); pulseHigh = false; }
    return;  // one pulse at a time
  }
  if (!armed) return;
  if (passMode) {
    noInterrupts();
    bool edge = projEdge; uint32_t at = projEdgeUs; projEdge = false;
    interrupts();
    if (edge && !pulsePending) { pulsePending = true; pulseAtUs = at + delayUs; }
  } else if (!pulsePending && (pulseCount == 0 || pulsesDone < pulseCount) &&
             (int32_t)(now - nextStartUs) >= 0) {
    pulsePending = true;
    pulseAtUs = nextStartUs + delayUs;
    nextStartUs += periodUs;
  }
  if (pulsePending && (int32_t)(now - pulseAtUs) >= 0) {
    digitalWrite(PIN_CAM_TRIGGER, HIGH);
    pulseHigh = true; pulsePending = false;
    pulseEndUs = now + widthUs;
    pulsesDone++;
  }
}

static void serviceSafety() {
  bool open = digitalRead(PIN_INTERLOCK) == HIGH;  // pull-up: open loop reads HIGH
  if (open != interlockOpen) {
    interlockOpen = open;
    if (open) { ledOn = -1; disarm(); Serial.println(F("# INTERLOCK open")); }
    else Serial.println(F("# INTERLOCK closed"));
    applyLeds();
  }
  bool active = armed || ledOn >= 0;
  if (active && (uint32_t)(millis() - lastOkMs) > wdtMs) {
    ledOn = -1; disarm(); tripped = true; applyLeds();
    Serial.println(F("# WATCHDOG tripped"));
  }
}

static void serviceSerial() {
  while (Serial.available() > 0) {
    char ch = (char)Serial.read();
    if (ch == '\r') continue;
    if (ch == '\n') {
      if (lineOverflow) err(6, F("line too long"));
      else { line[lineLen] = '\0'; if (execute(line)) lastOkMs = millis(); }
      lineLen = 0; lineOverflow = false;
    } else if (lineLen < MAX_LINE) {
      line[lineLen++] = ch;
    } else {
      lineOverflow = true;  // keep reading to the newline, then reply ERR 6
    }
  }
}

void setup() {
  wdt_disable();
  for (uint8_t c = 0; c < 3; c++) { pinMode(PIN_LED[c], OUTPUT); analogWrite(PIN_LED[c], 0); }
  pinMode(PIN_CAM_TRIGGER, OUTPUT); digitalWrite(PIN_CAM_TRIGGER, LOW);
  pinMode(PIN_STATUS, OUTPUT); digitalWrite(PIN_STATUS, LOW);
  pinMode(PIN_PROJ_TRIGGER, INPUT);
  pinMode(PIN_INTERLOCK, INPUT_PULLUP);
  attachInterrupt(digitalPinToInterrupt(PIN_PROJ_TRIGGER), onProjectorEdge, RISING);
  Serial.begin(115200);
  resetDefaults();
  interlockOpen = digitalRead(PIN_INTERLOCK) == HIGH;
  lastOkMs = millis();
  wdt_enable(WDTO_250MS);  // MCU hang -> reset -> outputs low: the hardware backstop
  Serial.println(F("# FRINGESCOPE LEDCTRL ready"));
}

void loop() {
  wdt_reset();
  serviceSerial();
  serviceSafety();
  serviceTrigger();
}
